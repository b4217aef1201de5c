//! The OpenAPI 3.1 document served at `/api/v1/openapi.json`. Written by hand next to
//! the routes; `tests/api.rs` checks that it lists exactly the router's routes.
use serde_json::{Value, json};

fn error_responses(codes: &[&str]) -> Value {
    let mut m = serde_json::Map::new();
    for c in codes {
        let text = match *c {
            "401" => "missing or wrong bearer token",
            "403" => "the daemon has no token configured, or the Host or Origin is not allowed",
            "404" => "unknown run, file or route",
            "409" => "the request does not fit the run's state",
            "413" => "body over the size limit",
            "415" => "body is not TOML",
            "422" => {
                "invalid capture plan (file, line and key named), or over the run budget (`over-budget`)"
            }
            "429" => "the queue is full (`[api] max-queue`)",
            "503" => "the instrument could not be reached, or the stream or download cap is reached",
            "500" => {
                "a file under the runs directory could not be read or written (`storage`, the path named), or the instrument config is invalid"
            }
            _ => "error",
        };
        m.insert(
            (*c).into(),
            json!({ "description": text, "content": { "application/json": { "schema": { "$ref": "#/components/schemas/Error" } } } }),
        );
    }
    Value::Object(m)
}

fn op(summary: &str, secured: bool, ok: (&str, Value), errors: &[&str], params: &[&str]) -> Value {
    let mut responses = error_responses(errors);
    responses[ok.0] = ok.1;
    let mut o = json!({
        "summary": summary,
        "responses": responses,
        "parameters": params.iter().map(|p| json!({
            "name": p, "in": "path", "required": true, "schema": { "type": "string" }
        })).collect::<Vec<_>>(),
    });
    if secured {
        o["security"] = json!([{ "bearer": [] }]);
    }
    o
}

fn json_ok(description: &str, schema: Value) -> Value {
    json!({ "description": description, "content": { "application/json": { "schema": schema } } })
}

fn run_ref() -> Value {
    json!({ "$ref": "#/components/schemas/RunStatus" })
}

/// The OpenAPI document.
pub fn openapi() -> Value {
    let object = json!({ "type": "object" });
    let files: Vec<&str> = super::DOWNLOADS.iter().map(|(n, _)| *n).collect();
    json!({
        "openapi": "3.1.0",
        "info": {
            "title": "Periscope instrument API",
            "version": env!("CARGO_PKG_VERSION"),
            "description": "Runs an NLOS imaging instrument: queue capture plans, follow their progress, download results. Mutating endpoints need `Authorization: Bearer <token>`."
        },
        "components": {
            "securitySchemes": { "bearer": { "type": "http", "scheme": "bearer" } },
            "schemas": {
                "Error": {
                    "type": "object",
                    "required": ["error", "message"],
                    "properties": {
                        "error": { "type": "string", "description": "machine-readable code, e.g. unknown-run" },
                        "message": { "type": "string", "description": "what went wrong and what to do" }
                    }
                },
                "RunStatus": {
                    "type": "object",
                    "required": ["id", "plan", "state", "stage", "pairs_total", "pairs_done", "progress", "files"],
                    "properties": {
                        "id": { "type": "string" },
                        "plan": { "type": "string" },
                        "state": { "type": "string", "enum": ["queued", "running", "paused", "completed", "aborted", "failed"] },
                        "stage": { "type": "string" },
                        "pairs_total": { "type": "integer" },
                        "pairs_done": { "type": "integer" },
                        "progress": { "type": "number", "minimum": 0, "maximum": 1 },
                        "eta_s": { "type": ["number", "null"] },
                        "queue_position": { "type": ["integer", "null"] },
                        "loss": { "type": ["number", "null"] },
                        "error": { "type": ["string", "null"] },
                        "timings": { "type": "array", "items": { "type": "array", "prefixItems": [{ "type": "string" }, { "type": "number" }] } },
                        "files": { "type": "array", "items": { "type": "string", "enum": files } }
                    }
                }
            }
        },
        "paths": {
            "/api/v1/health": { "get": op("Liveness and version", false, ("200", json_ok("daemon is up", object.clone())), &[], &[]) },
            "/api/v1/openapi.json": { "get": op("This document", false, ("200", json_ok("OpenAPI 3.1", object.clone())), &[], &[]) },
            "/api/v1/instrument": { "get": op("Devices, positions, laser and interlock state, count rates, as the worker last read them (`reading` gives when); never touches the hardware", false, ("200", json_ok("instrument status", object.clone())), &[], &[]) },
            "/api/v1/runs": {
                "post": {
                    "summary": "Submit a TOML capture plan; it is validated, then queued",
                    "security": [{ "bearer": [] }],
                    "requestBody": { "required": true, "content": { "application/toml": { "schema": { "type": "string" } } } },
                    "responses": {
                        "201": json_ok("queued; Location names the run", run_ref()),
                        "401": error_responses(&["401"])["401"], "403": error_responses(&["403"])["403"],
                        "413": error_responses(&["413"])["413"], "415": error_responses(&["415"])["415"],
                        "422": error_responses(&["422"])["422"], "429": error_responses(&["429"])["429"],
                        "500": error_responses(&["500"])["500"], "503": error_responses(&["503"])["503"]
                    }
                },
                "get": op("Every run, oldest first", false, ("200", json_ok("runs", json!({ "type": "array", "items": run_ref() }))), &[], &[])
            },
            "/api/v1/check": {
                "post": {
                    "summary": "What `periscope check` says about a TOML capture plan: the report, estimated durations, the run budget and targets outside the galvo limits; nothing is queued or touched",
                    "requestBody": { "required": true, "content": { "application/toml": { "schema": { "type": "string" } } } },
                    "responses": {
                        "200": json_ok("the plan is valid; `over_budget` says whether submit would refuse it", json!({ "type": "object", "required": ["plan", "report", "pairs", "duration_s", "memory_bytes", "disk_bytes", "memory_limit", "disk_limit", "problems"], "properties": {
                            "plan": { "type": "string" }, "report": { "type": "string" }, "pairs": { "type": "integer" },
                            "duration_s": { "type": "object", "properties": { "los": { "type": "number" }, "capture": { "type": "number" }, "reconstruction": { "type": "number" }, "total": { "type": "number" } } },
                            "memory_bytes": { "type": "integer" }, "disk_bytes": { "type": "integer" }, "memory_limit": { "type": "integer" }, "disk_limit": { "type": "integer" },
                            "over_budget": { "type": ["string", "null"] }, "problems": { "type": "array", "items": { "type": "string" } }
                        } })),
                        "401": error_responses(&["401"])["401"], "403": error_responses(&["403"])["403"],
                        "413": error_responses(&["413"])["413"], "415": error_responses(&["415"])["415"],
                        "422": error_responses(&["422"])["422"]
                    }
                }
            },
            "/api/v1/runs/{id}/geometry": { "get": op("A run's geometry for 3-D views: relay points, planned illumination and detection points (each thinned to at most 20,000), the volume box and the instrument's viewpoint, metres", false, ("200", json_ok("geometry", json!({ "type": "object", "properties": { "relay": { "type": "array" }, "illumination": { "type": "array" }, "detection": { "type": "array" }, "pairs": { "type": "integer" }, "volume": { "type": "object" }, "viewpoint": { "type": "array" } } }))), &["404"], &["id"]) },
            "/api/v1/runs/{id}": { "get": op("One run: state, stage, progress, ETA, files", false, ("200", json_ok("run", run_ref())), &["404"], &["id"]) },
            "/api/v1/runs/{id}/pause": { "post": op("Pause a running run at its next checkpoint (between pairs)", true, ("202", json_ok("pause requested", run_ref())), &["401", "403", "404", "409"], &["id"]) },
            "/api/v1/runs/{id}/resume": { "post": op("Queue a paused or failed run again; it continues from its last stored pair", true, ("202", json_ok("queued", run_ref())), &["401", "403", "404", "409"], &["id"]) },
            "/api/v1/runs/{id}/abort": { "post": op("Abort a run; what was captured is kept", true, ("202", json_ok("abort requested or done", run_ref())), &["401", "403", "404", "409"], &["id"]) },
            "/api/v1/estop": { "post": op("Emergency stop: laser off first (directly, out of band), then the running run aborted and both arms parked, queued runs held; every step is tried and reported", true, ("200", json_ok("instrument safe", json!({ "type": "object", "properties": { "aborted": { "type": ["string", "null"] }, "laser": { "type": "string" }, "laser_off_s": { "type": ["number", "null"] }, "parked": { "type": "boolean" }, "held": { "type": "array", "items": { "type": "string" } }, "warnings": { "type": "array", "items": { "type": "string" } }, "seconds": { "type": "number" } } }))), &["401", "403", "503"], &[]) },
            "/api/v1/runs/{id}/events": {
                "get": {
                    "summary": "Server-sent events: a `status` snapshot, then the run's typed events (stage-started, stage-finished, los-point, relay, planned, pair, histogram, initialised, data-added, epoch, snapshot, pruned, output, failed, completed; `lagged` if the client fell behind)",
                    "parameters": [{ "name": "id", "in": "path", "required": true, "schema": { "type": "string" } }],
                    "responses": {
                        "200": { "description": "event stream", "content": { "text/event-stream": { "schema": { "type": "string" } } } },
                        "404": error_responses(&["404"])["404"], "503": error_responses(&["503"])["503"]
                    }
                }
            },
            "/api/v1/runs/{id}/files/{name}": {
                "get": {
                    "summary": "Download a run file (volume .npy, depth/albedo PNG, PLY point cloud and Gaussians, y-tal HDF5 capture, ...)",
                    "parameters": [
                        { "name": "id", "in": "path", "required": true, "schema": { "type": "string" } },
                        { "name": "name", "in": "path", "required": true, "schema": { "type": "string", "enum": files } }
                    ],
                    "responses": {
                        "200": { "description": "the file", "content": { "application/octet-stream": { "schema": { "type": "string", "format": "binary" } } } },
                        "404": error_responses(&["404"])["404"], "503": error_responses(&["503"])["503"]
                    }
                }
            }
        }
    })
}
