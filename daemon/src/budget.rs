//! What a plan costs in memory and disk, checked against the instrument's `[budget]`
//! before anything runs: when a plan is submitted (422 over budget), by
//! `periscope check` (printed), and when a run starts.
//!
//! The figures are upper estimates from the plan's sizes, item by item, each naming
//! the plan keys that drive it, so an over-budget answer says what to shrink. They
//! follow how the pipeline holds its data:
//! - capture: every stored record (counts as `u32`) and the transient set the fit
//!   reads (`f32` per bin, plus its weight row), per pair;
//! - the solver's volume and its work arrays (complex FFT buffers padded to twice the
//!   volume along each axis for LCT and RSD: 16 bytes × 8 per voxel, the largest);
//! - 3D-GTR: the virtual confocal scan (`f64` per bin of its own time axis,
//!   [`VIRTUAL_SCAN_BINS`]), or with `virtual-scan = "splat"` the splatted apexes
//!   instead; LCT's or f-k's work arrays on that scan when either is the solver after
//!   the fit (the figures the solvers check themselves against); the primitives with
//!   their gradients and optimiser moments; and where the fit estimates per-transient
//!   gains, its rendering of the whole capture (`f64` per bin, and a GPU's `f32`);
//! - FBP run on the measured pairs: its filtered histograms;
//! - disk: the histogram log (a 36-byte header and 4 bytes per bin per pair), the y-tal
//!   export of the capture (4 bytes per bin per pair), the volume outputs, and the pair
//!   plan, event log and LOS rows.
use std::fmt::Write;

/// Most points per axis of a virtual scan grown to cover the volume (at the
/// virtual grid's pitch); beyond it the pitch coarsens.
pub const MAX_VIRTUAL_RESOLUTION: usize = 128;

/// Bins of the virtual confocal scan's time axis, from path length zero to past the
/// volume's farthest corner, whatever the capture's bins.
pub const VIRTUAL_SCAN_BINS: usize = 512;

use periscope_recon::solver::{SolverKind, fk_work_bytes, lct_work_bytes};
use periscope_recon::synth::splat_bytes;

use crate::plan::{Method, Plan, ReconSettings, VirtualScan};

/// Bytes in a GiB.
const GIB: f64 = (1u64 << 30) as f64;

/// Memory and disk limits for one run: the instrument config's `[budget]` table.
pub use crate::config::BudgetLimits as Limits;

/// One line of the estimate.
#[derive(Clone, Debug, PartialEq)]
pub struct Item {
    /// What it is.
    pub what: &'static str,
    /// The plan keys that size it.
    pub keys: &'static str,
    /// Bytes.
    pub bytes: u64,
}

impl Item {
    /// The first plan key that sizes it (`keys` up to its first space, comma or
    /// parenthesis): where a plan over budget is located in its file.
    pub fn plan_key(&self) -> &'static str {
        let end = self.keys.find([' ', ',', '(']).unwrap_or(self.keys.len());
        &self.keys[..end]
    }
}

/// A plan over its budget ([`Budget::check`]).
#[derive(Clone, Debug, PartialEq)]
pub struct OverBudget {
    /// The plan key that sizes the largest part of what is over: the plan file's
    /// error is located there.
    pub key: &'static str,
    /// What is over, by how much, and what to reduce.
    pub message: String,
}

impl std::fmt::Display for OverBudget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

/// A plan's estimated memory and disk needs, and how long it keeps the instrument.
#[derive(Clone, Debug, PartialEq)]
pub struct Budget {
    /// Memory items.
    pub memory: Vec<Item>,
    /// Disk items.
    pub disk: Vec<Item>,
    /// The LOS scan's and the capture's seconds at most
    /// ([`instrument_seconds`]); `None` for an import, which measures
    /// nothing.
    pub instrument: Option<(f64, f64)>,
}

/// `a × b × ...`, saturating (a hostile plan's sizes must not wrap to a small number).
fn mul(factors: &[u64]) -> u64 {
    factors.iter().fold(1u64, |a, &b| a.saturating_mul(b))
}

/// The reconstruction's memory: the volume and its solver's work arrays, and for
/// 3D-GTR its virtual scan, the solver after it, the gains' rendering and the
/// primitives (`pairs` × `bins` is the capture, 0 where it is not known yet).
pub fn recon_items(recon: &ReconSettings, pairs: u64, bins: u64, estimates_gains: bool) -> Vec<Item> {
    let voxels = mul(&recon.volume.shape.map(|n| n as u64));
    let mut memory = vec![Item {
        what: "volume and solver work arrays",
        keys: "recon.volume.shape",
        bytes: mul(&[voxels, 16 * 8 + 8]),
    }];
    if recon.method == Method::Gtr {
        // Without a virtual-size the grid may grow to cover the volume, and without
        // a virtual-grid its points follow the voxels: either way up to the cap per
        // axis.
        let most = MAX_VIRTUAL_RESOLUTION;
        let virt = match recon.virtual_resolution {
            Some(res) if recon.virtual_size.is_some() => mul(&res.map(|n| n as u64)),
            Some(res) => mul(&res.map(|n| n.max(most) as u64)),
            None => mul(&[most as u64, most as u64]),
        };
        const GRID: &str = "recon.gtr.virtual-grid (default one point per voxel pitch after fbp, 64 × 64 after lct, fk and rsd; grown to cover the volume, up to 128 per axis)";
        let m = VIRTUAL_SCAN_BINS as u64;
        let cells = usize::try_from(virt).unwrap_or(usize::MAX);
        let to_u64 = |b: usize| u64::try_from(b).unwrap_or(u64::MAX);
        let solver = recon.solver;
        if solver == SolverKind::Lct && recon.virtual_scan == VirtualScan::Splat {
            memory.push(Item {
                what: "3D-GTR splatted light cones",
                keys: GRID,
                bytes: to_u64(splat_bytes(cells, VIRTUAL_SCAN_BINS)),
            });
        } else {
            memory.push(Item {
                what: "3D-GTR virtual confocal scan",
                keys: GRID,
                bytes: mul(&[virt, m, 8 * 2]),
            });
        }
        match solver {
            SolverKind::Lct => memory.push(Item {
                what: "LCT on the virtual scan",
                keys: GRID,
                bytes: to_u64(lct_work_bytes(cells, VIRTUAL_SCAN_BINS)),
            }),
            SolverKind::Fk => memory.push(Item {
                what: "f-k migration on the virtual scan",
                keys: GRID,
                bytes: to_u64(fk_work_bytes(cells, VIRTUAL_SCAN_BINS)),
            }),
            _ => {}
        }
        if estimates_gains {
            memory.push(Item {
                what: "3D-GTR gain estimation's rendering of the capture",
                keys: "pairs × acquisition.bins, where the fit estimates gains (recon.gtr.pair-gains; relay.albedo-from-scan)",
                // f64 per bin, and on a GPU its f32 copy as it comes back.
                bytes: mul(&[pairs, bins, 12]),
            });
        }
        memory.push(Item {
            what: "3D-GTR primitives, gradients and optimiser state",
            keys: "recon.gtr.primitives",
            bytes: mul(&[recon.train.primitives as u64, 14 * 8 * 4]),
        });
    }
    memory
}

/// A solver run on the measured pairs (`method` a solver's name): what it holds
/// beside the capture. FBP holds each pair's filtered histogram (a complex pair of
/// f32) and then its doubled copy (f64) while that is still there, 24 B a bin beside
/// the capture (less the envelope's padding at either end). LCT's and f-k's cubes
/// depend on the grid the relay scan finds and the volume's paths from it, known only
/// once the run has planned its pairs, so they are not costed here (`volume and
/// solver work arrays` holds their volume). Until 2026-12-07 FBP's copies were not
/// counted either.
fn direct_solver_items(plan: &Plan) -> Vec<Item> {
    match plan.recon.method {
        Method::Solver(SolverKind::Fbp) => vec![Item {
            what: "FBP's filtered histograms",
            keys: "pairs × acquisition.bins",
            bytes: mul(&[
                plan.pairs.max_pairs() as u64,
                u64::from(plan.acquisition.bins),
                24,
            ]),
        }],
        _ => Vec::new(),
    }
}

/// Software overhead per measured point (moves, acquisition, storage), seconds; the
/// driver benchmark measures about 0.2 ms against the simulator, a real 115200-baud
/// link adds about 3 ms per exchange.
const OVERHEAD_SIM: f64 = 0.3e-3;
const OVERHEAD_SERIAL: f64 = 6e-3;
/// 3D-GTR forward+backward evaluations (pair × primitive) per optimiser step's pairs,
/// per second, offline after a capture (release, 2 cores: `cargo bench -p
/// periscope-daemon --bench scaling`, 1,000 to 16,000 pairs at 64³: 14.6–16 million;
/// docs/recon.md, "How cost grows with the work").
pub(crate) const GTR_EVALS_PER_S: f64 = 1.5e7;
/// Synthesis evaluations (virtual point × primitive) per second (`--bench solvers`,
/// 64 × 64 points × 10,000 primitives in 1.46 s).
pub(crate) const SYNTH_EVALS_PER_S: f64 = 2.8e7;

/// How long `plan` keeps the instrument, seconds: its LOS scan, its capture at most
/// and, for an adaptive capture that a stopping rule may end early, at least. The
/// device time the plan's dwells, settling and each pair's overhead add up to (times
/// the simulator's time scale), and an adaptive capture's waits for its choices.
pub fn instrument_seconds(plan: &Plan, inst: &crate::config::InstrumentConfig) -> (f64, f64, Option<f64>) {
    let (l, a, rc) = (&plan.los, &plan.acquisition, &plan.recon);
    let candidates = plan.pairs.max_pairs();
    let adaptive = plan
        .adaptive
        .then(|| crate::adaptive::Sizes::of(candidates, &plan.recon.adaptive));
    let pairs = adaptive.map_or(candidates, |s| s.budget);
    let sim = matches!(inst.backend, crate::config::Backend::Sim(_));
    let overhead = if sim { OVERHEAD_SIM } else { OVERHEAD_SERIAL };
    let scale = match &inst.backend {
        crate::config::Backend::Sim(s) => s.time_scale,
        crate::config::Backend::Hardware => 1.0,
    };
    let settle = inst.laser_arm.settle.max(inst.spad_arm.settle).as_secs_f64();
    let los_s = (l.grid[0] * l.grid[1]) as f64 * ((l.dwell.as_secs_f64() + settle) * scale + overhead);
    // Each repeat is an acquisition of its own (a checkpoint and the counter's round
    // trip), so the overhead is a repeat's.
    let per_pair =
        (a.dwell.as_secs_f64() * f64::from(a.repeats) + settle) * scale + overhead * f64::from(a.repeats);
    let cap_s = pairs as f64 * per_pair;
    // An adaptive capture waits, laser off, for each choice: the batch's live training
    // and the scoring of every candidate against every primitive.
    let choice_s = |rounds: usize| {
        let k = rc.train.primitives as f64;
        rounds as f64
            * (rc.adaptive.live_steps as f64 * rc.train.batch_size as f64 * k / GTR_EVALS_PER_S
                + candidates as f64 * k / SYNTH_EVALS_PER_S)
    };
    let (cap_s, cap_min_s) = match adaptive {
        None => (cap_s, None),
        Some(s) => (
            // A time budget ends the choosing, judged after each batch's live training:
            // the first batch always runs whole, and the choice and batch under way when
            // the budget runs out are finished.
            match rc.adaptive.seconds {
                t if t > 0.0 => (cap_s + choice_s(s.rounds())).min(
                    (s.first as f64 * per_pair + choice_s(1))
                        .max(t + choice_s(1) + s.batch as f64 * per_pair),
                ),
                _ => cap_s + choice_s(s.rounds()),
            },
            // The stopping rule can end it at the second choice: the first sets the
            // reference its gain is judged against (a relative gain of 1), so one
            // chosen batch is always measured.
            (rc.adaptive.stop_gain > 0.0 && s.rounds() > 0).then(|| {
                (s.first + s.batch.min(s.budget - s.first)) as f64 * per_pair + choice_s(s.rounds().min(2))
            }),
        ),
    };
    (los_s, cap_s, cap_min_s)
}

/// Seconds as a reader takes them: `45 s`, `12.5 min`, `3.2 h`, `4.1 days`.
fn span(seconds: f64) -> String {
    if seconds < 10.0 {
        format!("{seconds:.2} s")
    } else if seconds < 60.0 {
        format!("{seconds:.0} s")
    } else if seconds < 3600.0 {
        format!("{:.1} min", seconds / 60.0)
    } else if seconds < 48.0 * 3600.0 {
        format!("{:.1} h", seconds / 3600.0)
    } else {
        format!("{:.1} days", seconds / 86400.0)
    }
}

fn gib(bytes: u64) -> String {
    let g = bytes as f64 / GIB;
    if g >= 0.1 {
        format!("{g:.1} GiB")
    } else {
        format!("{:.1} MiB", bytes as f64 / (1u64 << 20) as f64)
    }
}

impl Budget {
    /// The estimate for reconstructing an imported capture with `recon`, before the
    /// capture is read (its own size is checked as it is read): the volume and the
    /// fit, memory and the volume's outputs on disk.
    pub fn of_import(recon: &ReconSettings) -> Budget {
        let voxels = mul(&recon.volume.shape.map(|n| n as u64));
        Budget {
            memory: recon_items(recon, 0, 0, false),
            disk: vec![Item {
                what: "volume outputs",
                keys: "recon.volume.shape",
                bytes: mul(&[voxels, 4]),
            }],
            instrument: None,
        }
    }

    /// The estimate for `plan` on `inst`.
    pub fn of_plan(plan: &Plan, inst: &crate::config::InstrumentConfig) -> Budget {
        let pairs = plan.pairs.max_pairs() as u64;
        let bins = u64::from(plan.acquisition.bins);
        let voxels = mul(&plan.recon.volume.shape.map(|n| n as u64));
        let los = mul(&plan.los.grid.map(|n| n as u64));
        let mut memory = vec![
            Item {
                what: "captured histograms and transients",
                keys: "pairs (grid, laser-grid, count, mask) × acquisition.bins",
                // u32 record + f32 transient + f32 weight per bin, and per-pair
                // geometry (a few hundred bytes).
                bytes: mul(&[pairs, bins, 12]).saturating_add(mul(&[pairs, 512])),
            },
            Item {
                what: "LOS scan",
                keys: "los.grid × acquisition.bins",
                bytes: mul(&[los, bins.max(1), 8]).saturating_add(mul(&[los, 256])),
            },
        ];
        memory.extend(recon_items(&plan.recon, pairs, bins, plan.estimates_gains()));
        memory.extend(direct_solver_items(plan));
        if plan.adaptive {
            memory.push(Item {
                what: "adaptive capture's choice of each batch",
                keys: "pairs.mode = \"adaptive\", recon.gtr.primitives",
                bytes: crate::adaptive::choice_bytes(plan.pairs.max_pairs(), plan.recon.train.primitives),
            });
        }
        let disk = vec![
            Item {
                what: "histogram log",
                keys: "pairs × acquisition.bins",
                bytes: mul(&[pairs, bins.saturating_mul(4).saturating_add(36)]),
            },
            Item {
                what: "y-tal capture export",
                keys: "pairs × acquisition.bins",
                bytes: mul(&[pairs, bins, 4]).saturating_add(mul(&[pairs, 48])),
            },
            Item {
                what: "volume outputs",
                keys: "recon.volume.shape",
                bytes: mul(&[voxels, 4]),
            },
            Item {
                // pairs.json (up to about 420 B a pair), a `pair` line in events.jsonl
                // (about 110 B), and los.jsonl (up to 128 B a point): small beside the
                // log, but not nothing at millions of pairs (until 2026-12-07 none was
                // counted).
                what: "pair plan, event log and LOS rows",
                keys: "pairs (grid, laser-grid, count, mask), los.grid",
                bytes: mul(&[pairs, 530]).saturating_add(mul(&[los, 128])),
            },
        ];
        let (los, capture, _) = instrument_seconds(plan, inst);
        Budget {
            memory,
            disk,
            instrument: Some((los, capture)),
        }
    }

    /// The instrument time, seconds (0 for an import).
    pub fn instrument_seconds(&self) -> f64 {
        self.instrument.map_or(0.0, |(los, capture)| los + capture)
    }

    /// Total memory, bytes.
    pub fn memory_bytes(&self) -> u64 {
        self.memory.iter().fold(0u64, |a, i| a.saturating_add(i.bytes))
    }

    /// Total disk, bytes.
    pub fn disk_bytes(&self) -> u64 {
        self.disk.iter().fold(0u64, |a, i| a.saturating_add(i.bytes))
    }

    /// Refuses a plan over `limits`, naming the largest item, its plan keys and the
    /// numbers.
    pub fn check(&self, limits: &Limits) -> Result<(), OverBudget> {
        for (kind, items, total, limit, key) in [
            (
                "memory",
                &self.memory,
                self.memory_bytes(),
                limits.memory,
                "budget.memory-gib",
            ),
            (
                "disk",
                &self.disk,
                self.disk_bytes(),
                limits.disk,
                "budget.disk-gib",
            ),
        ] {
            if total > limit {
                let top = items
                    .iter()
                    .max_by_key(|i| i.bytes)
                    .expect("items are never empty");
                return Err(OverBudget {
                    key: top.plan_key(),
                    message: format!(
                        "over budget: the plan needs {} of {kind}, more than the instrument's {} \
                         (`{}` in the instrument config); the largest part is the {} ({}), sized by {}: \
                         reduce those",
                        gib(total),
                        gib(limit),
                        key,
                        top.what,
                        gib(top.bytes),
                        top.keys
                    ),
                });
            }
        }
        if let (Some(hours), Some((los, capture))) = (limits.hours, self.instrument)
            && los + capture > hours * 3600.0
        {
            return Err(OverBudget {
                // Where the longer part is sized.
                key: if los > capture { "los.grid" } else { "pairs" },
                message: format!(
                    "over budget: the plan keeps the instrument about {} (LOS scan {}, capture {} at most), \
                     more than the instrument's {} (`budget.hours` in the instrument config): fewer pairs \
                     (pairs grid, laser-grid, count or mask), a shorter acquisition.dwell-ms or fewer \
                     acquisition.repeats, or a smaller los.grid",
                    span(los + capture),
                    span(los),
                    span(capture),
                    span(hours * 3600.0)
                ),
            });
        }
        Ok(())
    }

    /// The estimate as `periscope check` prints it.
    pub fn report(&self, limits: &Limits) -> String {
        let mut out = String::new();
        for (kind, items, total, limit) in [
            ("memory", &self.memory, self.memory_bytes(), limits.memory),
            ("disk", &self.disk, self.disk_bytes(), limits.disk),
        ] {
            let _ = writeln!(
                out,
                "  {kind}: {} of {} budget{}",
                gib(total),
                gib(limit),
                if total > limit { " — OVER BUDGET" } else { "" }
            );
            for i in items {
                let _ = writeln!(out, "    {:>10}  {} ({})", gib(i.bytes), i.what, i.keys);
            }
        }
        if let Some((los, capture)) = self.instrument {
            let total = los + capture;
            let _ = writeln!(
                out,
                "  instrument time: {} (LOS scan and capture at most) of {}{}",
                span(total),
                limits
                    .hours
                    .map_or("no budget (`budget.hours` unset)".to_owned(), |h| format!(
                        "{} budget",
                        span(h * 3600.0)
                    )),
                if limits.hours.is_some_and(|h| total > h * 3600.0) {
                    " — OVER BUDGET"
                } else {
                    ""
                }
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The demo plan (LCT after 3D-GTR, a 64 × 64 virtual grid) with `edit` applied to
    /// its text.
    fn demo_budget(edit: impl Fn(&str) -> String) -> Budget {
        demo_budget_on("", edit)
    }

    /// [`demo_budget`] on the simulator with `sim` added to its `[sim]` table.
    fn demo_budget_on(sim: &str, edit: impl Fn(&str) -> String) -> Budget {
        use crate::config::{InstrumentConfig, TomlSource};
        let instrument = InstrumentConfig::from_source(&TomlSource::from_text(
            "sim.toml",
            include_str!("../../configs/instrument/sim.toml").replace("[sim]\n", &format!("[sim]\n{sim}\n")),
        ))
        .unwrap();
        let text = edit(include_str!("../../configs/plans/demo.toml"));
        let plan = Plan::from_source(&TomlSource::from_text("demo.toml", &text), &instrument).unwrap();
        Budget::of_plan(&plan, &instrument)
    }

    fn item(b: &Budget, what: &str) -> Option<u64> {
        b.memory.iter().find(|i| i.what == what).map(|i| i.bytes)
    }

    #[test]
    fn the_virtual_scan_and_its_solver_are_costed_as_the_pipeline_holds_them() {
        // Without a `virtual-size` the 64 × 64 grid may grow to cover the volume, up to
        // the cap per axis.
        let cells = MAX_VIRTUAL_RESOLUTION * MAX_VIRTUAL_RESOLUTION;
        let m = VIRTUAL_SCAN_BINS;
        let scan = (cells * m * 16) as u64;
        // LCT after 3D-GTR, the scan rendered: the scan on its own 512 bins (not the
        // acquisition's), and LCT's padded spectra on it.
        let render = demo_budget(|t| t.to_string());
        assert_eq!(item(&render, "3D-GTR virtual confocal scan"), Some(scan));
        let lct = item(&render, "LCT on the virtual scan").expect("LCT's work arrays");
        assert_eq!(lct, ((m + 1) * 4 * cells * 8 + cells * m * 8) as u64);
        assert_eq!(item(&render, "3D-GTR splatted light cones"), None);
        // The acquisition's bins do not size the virtual scan.
        let more_bins = demo_budget(|t| t.replace("repeats = 1", "repeats = 1\nbins = 4096"));
        assert_eq!(item(&more_bins, "3D-GTR virtual confocal scan"), Some(scan));
        // Splatted: no scan, the apexes and at most one grid-wide primitive's deposits.
        let splat = demo_budget(|t| {
            t.replace(
                "virtual-grid = [64, 64]",
                "virtual-grid = [64, 64]\nvirtual-scan = \"splat\"",
            )
        });
        assert_eq!(item(&splat, "3D-GTR virtual confocal scan"), None);
        let cones = item(&splat, "3D-GTR splatted light cones").expect("the splat's apexes");
        assert_eq!(
            cones,
            (cells * m * 4 + (cells * m * 4 + cells * 32).max(8 << 20)) as u64
        );
        assert!(cones < scan, "{cones} ≥ {scan}");
        assert_eq!(item(&splat, "LCT on the virtual scan"), Some(lct));
        // FBP after the fit works on the volume: no solver item on the scan.
        let fbp = demo_budget(|t| t.replace("solver = \"lct\"", "solver = \"fbp\""));
        assert_eq!(item(&fbp, "3D-GTR virtual confocal scan"), Some(scan));
        assert_eq!(item(&fbp, "LCT on the virtual scan"), None);
        let fk = demo_budget(|t| t.replace("solver = \"lct\"", "solver = \"fk\""));
        assert_eq!(
            item(&fk, "f-k migration on the virtual scan"),
            Some(((m + 1) * 8 * cells * 8 + cells * m * 4) as u64)
        );
    }

    #[test]
    fn the_gain_rounds_rendering_is_costed_where_the_fit_estimates_gains() {
        const WHAT: &str = "3D-GTR gain estimation's rendering of the capture";
        // The demo takes its gains from the relay scan: nothing to estimate.
        assert_eq!(item(&demo_budget(|t| t.to_string()), WHAT), None);
        // Without the scan's albedo, `auto` estimates them: the capture's pairs × bins
        // in f64, and a GPU's f32 copy.
        let no_scan = |t: &str| t.replacen("[relay]\n", "[relay]\nalbedo-from-scan = false\n", 1);
        let b = demo_budget(no_scan);
        let bins = 1024; // the simulated instrument's
        assert_eq!(item(&b, WHAT), Some(24 * 24 * bins * 12));
        let off =
            demo_budget(|t| no_scan(t).replacen("[recon.gtr]\n", "[recon.gtr]\npair-gains = \"none\"\n", 1));
        assert_eq!(item(&off, WHAT), None);
    }

    /// A solver run on the measured pairs is costed beside the capture (until
    /// 2026-12-07 only the volume was): FBP's filtered histograms at 24 B a bin of each
    /// pair; and the disk counts the pair
    /// plan, the event log's pair lines and the LOS rows; an adaptive capture, its
    /// choices' scoring.
    #[test]
    fn a_direct_solver_and_the_runs_small_files_are_costed() {
        let demo = |method: &str| {
            demo_budget_on("", |t| {
                // The demo without its fit's settings (the last table), solved directly.
                t[..t.find("[recon.gtr]").unwrap()]
                    .replace("method = \"gtr\"", &format!("method = \"{method}\""))
                    .replace("offset-mm = 5.0", "offset-mm = 0.0")
                    .replace("solver = \"lct\"\n", "")
            })
        };
        let fbp = demo("fbp");
        let (pairs, bins) = (576u64, 1024u64);
        assert_eq!(item(&fbp, "FBP's filtered histograms"), Some(pairs * bins * 24));
        assert!(item(&demo("lct"), "FBP's filtered histograms").is_none());
        let small = fbp
            .disk
            .iter()
            .find(|i| i.what == "pair plan, event log and LOS rows");
        assert!(small.is_some_and(|i| i.bytes >= pairs * 530), "{:?}", fbp.disk);
        // An adaptive capture's choices: the scored terms of its 576 candidates (at
        // most 8,192 are scored, about 160 MiB).
        let adaptive = demo_budget_on("", |t| {
            t.replace(
                "mode = \"confocal\"",
                "mode = \"adaptive\"\ncandidates = \"confocal\"",
            )
        });
        let what = "adaptive capture's choice of each batch";
        assert!(item(&adaptive, what).is_some_and(|b| b > pairs * 512 * 40 && b < 40 << 20));
        assert!(item(&demo_budget_on("", |t| t.to_owned()), what).is_none());
    }

    #[test]
    fn saturating_products_never_wrap_to_small_numbers() {
        assert_eq!(mul(&[u64::MAX, 2]), u64::MAX);
        assert_eq!(mul(&[1 << 40, 1 << 40]), u64::MAX);
        assert_eq!(mul(&[3, 4, 5]), 60);
    }

    #[test]
    fn over_budget_names_the_largest_item_and_its_keys() {
        let b = Budget {
            memory: vec![
                Item {
                    what: "a",
                    keys: "k.a",
                    bytes: 1 << 30,
                },
                Item {
                    what: "b",
                    keys: "k.b",
                    bytes: 20 << 30,
                },
            ],
            disk: vec![Item {
                what: "c",
                keys: "k.c",
                bytes: 1,
            }],
            instrument: None,
        };
        let over = b.check(&Limits::default()).unwrap_err();
        assert_eq!(over.key, "k.b");
        let e = over.to_string();
        assert!(e.contains("21.0 GiB of memory"), "{e}");
        assert!(e.contains("budget.memory-gib"), "{e}");
        assert!(e.contains("k.b") && !e.contains("k.a"), "{e}");
        assert!(
            b.check(&Limits {
                memory: 32 << 30,
                disk: 1,
                hours: None,
            })
            .is_ok()
        );
    }

    /// Every item's plan key is a key a plan file can hold, so an error located there
    /// points at a line of the plan (or its table).
    #[test]
    fn every_items_plan_key_is_a_plan_key() {
        let b = demo_budget(|t| {
            t.replace(
                "mode = \"confocal\"",
                "mode = \"adaptive\"\ncandidates = \"confocal\"",
            )
        });
        let keys: Vec<&str> = b.memory.iter().chain(&b.disk).map(Item::plan_key).collect();
        for key in &keys {
            assert!(
                !key.is_empty()
                    && key
                        .chars()
                        .all(|c| c.is_ascii_lowercase() || c == '.' || c == '-'),
                "{key:?} in {keys:?}"
            );
        }
        for want in [
            "pairs",
            "los.grid",
            "recon.volume.shape",
            "recon.gtr.primitives",
            "pairs.mode",
        ] {
            assert!(keys.contains(&want), "no {want} in {keys:?}");
        }
    }

    /// `budget.hours` bounds the time a plan keeps the instrument, by the estimate
    /// `periscope check` prints (the demo: 576 pairs of 20 ms and 1,024 LOS points of
    /// 1 ms on the simulator in real time); unset, nothing is refused.
    #[test]
    fn a_plan_that_keeps_the_instrument_too_long_is_over_budget() {
        let real_time = "time-scale = 1.0";
        let b = demo_budget_on(real_time, |t| t.to_owned());
        let seconds = b.instrument_seconds();
        assert!((10.0..60.0).contains(&seconds), "{seconds}");
        let limits = |hours| Limits {
            hours,
            ..Limits::default()
        };
        assert!(b.check(&limits(None)).is_ok());
        assert!(b.check(&limits(Some(seconds / 3600.0 * 1.01))).is_ok());
        let over = b.check(&limits(Some(seconds / 3600.0 * 0.99))).unwrap_err();
        // The capture is the longer part: the plan file's error is located at `pairs`.
        assert_eq!(over.key, "pairs");
        let e = over.to_string();
        assert!(
            e.contains("budget.hours") && e.contains("acquisition.dwell-ms") && e.contains("LOS scan"),
            "{e}"
        );
        assert!(b.report(&limits(Some(0.001))).contains("OVER BUDGET"));
        // A thousand repeats of a microsecond: each is an acquisition of its own, with
        // its overhead (0.3 ms on the simulator), so 576 pairs take at least 173 s more;
        // the estimate took the overhead once a pair until 2026-12-07.
        let repeated = demo_budget_on(real_time, |t| {
            t.replace("dwell-ms = 20.0", "dwell-ms = 0.001")
                .replace("repeats = 1 ", "repeats = 1000 ")
        });
        let short = demo_budget_on(real_time, |t| t.replace("dwell-ms = 20.0", "dwell-ms = 0.001"));
        let more = repeated.instrument_seconds() - short.instrument_seconds();
        assert!(more >= 576.0 * 999.0 * 0.3e-3, "{more} s");
        // A dwell of 20 s instead of 20 ms: about 3.2 hours.
        let long = demo_budget_on(real_time, |t| t.replace("dwell-ms = 20.0", "dwell-ms = 20000.0"));
        let e = long.check(&limits(Some(1.0))).unwrap_err().to_string();
        assert!(e.contains("about 3.2 h"), "{e}");
    }
}
