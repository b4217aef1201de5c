// The Periscope dashboard: the instrument, the queue, a live run and its results, all
// through the JSON API at /api/v1 with the token the operator types once per tab.
import { View3D, boxEdges } from '/ui/view3d.js';
import { startSafety } from '/ui/safety.js';
import { readEvents, silenceWatchdog } from '/ui/sse.js';

const $ = (id) => document.getElementById(id);
const TOKEN_KEY = 'periscope-token';
const POLL_MS = 2000;
// How long a poll waits for the daemon's answer (headers and body). A daemon that
// accepts connections and never answers must not leave the page showing what it read
// last: the E-STOP label and the connection pill say so instead.
const POLL_TIMEOUT_MS = 6000;
// A run's event stream with nothing on it for this long, not even the daemon's
// keep-alive comment (sent after 15 s without an event), is given up and opened
// again: a connection gone silent (a stalled proxy, a network that dropped it without
// a reset) would otherwise show a live run as frozen for good.
const RUN_STREAM_SILENT_MS = 40000;

// What the browser test reads.
const probe = {
  ready: false,
  loadMs: null,
  latencies: [],
  histograms: 0,
  lossPoints: 0,
  snapshots: 0,
  // An adaptive capture's pairs chosen so far, and its batches.
  chosen: 0,
  chosenBatches: 0,
  resultsShown: false,
  sliceShown: false,
  streamsOpened: 0,
  lastEvent: null,
  // Run files fetched, by name: results load lazily and the event log once.
  fetched: {},
  safety: 'unknown',
};
window.periscope = probe;

// ---------------------------------------------------------------- token and requests

let token = sessionStorage.getItem(TOKEN_KEY);

function showTokenState(message) {
  const state = $('token-state');
  if (token) {
    state.textContent = 'token set for this tab';
    state.className = 'ok';
    $('token-form').classList.remove('needed');
  } else {
    state.textContent = message || 'enter the API token to control the instrument';
    state.className = 'warn';
    $('token-form').classList.add('needed');
  }
}

$('token-form').addEventListener('submit', (e) => {
  e.preventDefault();
    const value = $('token').value.trim();
  // A header carries ISO-8859-1 only: a pasted curly quote would make every request
  // fail in the browser, e-stop included.
  if (/[^\x21-\x7e]/.test(value)) {
    $('token').value = '';
    showTokenState('that key has characters a key never has (spaces, quotes, accents): paste it again');
    return;
  }
  token = value || null;
  if (token) sessionStorage.setItem(TOKEN_KEY, token);
  else sessionStorage.removeItem(TOKEN_KEY);
  $('token').value = '';
  showTokenState();
  refresh();
});

function headers(extra = {}) {
  if (token) extra.Authorization = `Bearer ${token}`;
  return extra;
}

class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

// The page's requests other than its two streams, so the E-STOP can cancel them: a
// browser has six connections per host, and polls or an upload waiting on a loaded
// daemon must not hold the one the E-STOP needs. With `timeoutMs` a request (its body
// included) fails with a TimeoutError when the daemon has not answered in that time.
// With `read` (a function of the response), the request stays cancellable until
// `read` has read the body, and its result is returned. A `signal` in `init` cancels
// it too (the selected run's loads, when another run is chosen).
const inflight = new Set();
// When the daemon last answered one of the page's requests (its status and headers
// came, whatever the status): a poll that times out says the daemon is not answering
// only if nothing was answered after it went out (`pollTimedOut`).
let answeredAt = -Infinity;
async function pageFetch(path, init = {}, timeoutMs = null, read = null) {
  const ctl = new AbortController();
  const signals = [ctl.signal];
  if (init.signal) signals.push(init.signal);
  if (timeoutMs != null) signals.push(AbortSignal.timeout(timeoutMs));
  const signal = signals.length === 1 ? ctl.signal : AbortSignal.any(signals);
  inflight.add(ctl);
  try {
    const r = await fetch(path, { ...init, signal });
    answeredAt = performance.now();
    return read ? await read(r) : r;
  } finally {
    inflight.delete(ctl);
  }
}
function cancelPageRequests() {
  for (const ctl of inflight) ctl.abort();
  inflight.clear();
}
// Whether an error is a request given up (cancelled for the E-STOP, or timed out),
// not an answer.
const givenUp = (e) => e?.name === 'AbortError' || e?.name === 'TimeoutError';

// A 401 to a request sent with the key `sent` (null: none): the page asks for the key
// again, and forgets `sent` if it is still the key in use. A 401 that comes late, to a
// request sent before the operator entered another key, leaves the new key alone: its
// own requests say whether it is good.
function unauthorized(sent, message) {
  if (token !== sent) return;
  if (token) {
    token = null;
    sessionStorage.removeItem(TOKEN_KEY);
  }
  showTokenState(`the daemon wants the API token: ${message}`);
}

// The error for a refused request, with the daemon's own words where its body is the
// API's JSON error (`{error, message}`); a 401 asks for the key (`unauthorized`).
function refusal(r, json, sent) {
  const message = json?.message || `${r.status} ${r.statusText}`;
  if (r.status === 401) unauthorized(sent, message);
  return new ApiError(r.status, json?.error, message);
}

// A response's JSON body, or null where it has none (or it does not parse); a request
// given up while its body was read throws.
async function jsonBody(r) {
  try {
    return await r.json();
  } catch (e) {
    if (givenUp(e)) throw e;
    return null;
  }
}

// `timeoutMs`: for the polls (POLL_TIMEOUT_MS); a request that changes something, or
// reads a run's files, waits for its answer. `signal`: cancels it (another run chosen).
async function api(method, path, body, timeoutMs = null, signal = null) {
  // The key this request goes out with, for its 401 (`unauthorized`).
  const sent = token;
  const init = { method, headers: headers(body === undefined ? {} : { 'Content-Type': 'application/toml' }) };
  if (body !== undefined) init.body = body;
  if (signal) init.signal = signal;
  const r = await pageFetch(path, init, timeoutMs);
  const json = await jsonBody(r);
  if (!r.ok) throw refusal(r, json, sent);
  return json;
}

// A file larger than a caller's limit (`fetchBytes`), refused before its body is read
// where its length is given; `bytes` is null where it was not.
class TooLarge extends Error {
  constructor(name, bytes, limit) {
    super(`${name} is ${bytes == null ? 'larger than' : `${fmtBytes(bytes)}, over`} the ${fmtBytes(limit)} this page loads`);
    this.name = 'TooLarge';
  }
}

// A run file's bytes; the E-STOP cancels the download, body included, and so does
// `signal`. A file over `limit` bytes is refused with TooLarge: from its
// Content-Length before its body is read, or, where the length is not given (a
// compressed body), as soon as more has come. With a limit the body is read piece by
// piece into one buffer: Chromium's `arrayBuffer()` assembles a large body in one task
// of the page's thread (150 ms for 192 MiB), during which the E-STOP button does not
// answer. A refusal carries the daemon's own message (a 503 `too-many-downloads` says
// to retry shortly), and a 401 asks for the key as `api` does.
//
// With `from` above 0 only the bytes from there on are asked for (`Range: bytes=N-`,
// the event log read on from where the page left it). The answer is { bytes, from,
// length, pastEnd }: `from` where `bytes` start in the file (0 where the daemon sent
// the whole file, a 200), and `length` the file's length where the daemon gave it. A
// range that starts at or past the file's end is 416 with `Content-Range: bytes
// */length`, returned with `pastEnd` and no bytes: nothing new where `length` is
// `from`, a shorter file (written anew) where it is less.
async function fetchFile(path, { limit = Infinity, from = 0, signal = null } = {}) {
  const name = path.split('/').pop();
  probe.fetched[name] = (probe.fetched[name] || 0) + 1;
  // The key this request goes out with, for its 401 (`unauthorized`).
  const sent = token;
  // A range is read past the browser's cache: the daemon's answer is the file now.
  const init = from > 0 ? { headers: headers({ Range: `bytes=${from}-` }), cache: 'no-store' } : { headers: headers() };
  if (signal) init.signal = signal;
  return pageFetch(path, init, null, async (r) => {
    if (from > 0 && r.status === 416) {
      r.body?.cancel().catch(() => {});
      const m = /^bytes \*\/(\d+)$/.exec(r.headers.get('Content-Range') || '');
      return { bytes: new ArrayBuffer(0), from, length: m ? Number(m[1]) : null, pastEnd: true };
    }
    if (!r.ok) {
      const json = await jsonBody(r);
      const e = refusal(r, json, sent);
      e.message = `${name}: ${e.message}`;
      throw e;
    }
    let start = 0;
    let length = null;
    if (r.status === 206) {
      const m = /^bytes (\d+)-\d+\/(\d+)$/.exec(r.headers.get('Content-Range') || '');
      start = m ? Number(m[1]) : from;
      length = m ? Number(m[2]) : null;
    }
    if (limit === Infinity) return { bytes: await r.arrayBuffer(), from: start, length };
    const given = r.headers.get('Content-Encoding') ? null : r.headers.get('Content-Length');
    const size = given == null ? null : Number(given);
    if (size > limit) {
      r.body?.cancel().catch(() => {});
      throw new TooLarge(name, size, limit);
    }
    return { bytes: await readBody(r.body.getReader(), name, size, limit), from: start, length };
  });
}

// A whole run file's bytes (`fetchFile`).
async function fetchBytes(path, limit = Infinity, signal = null) {
  return (await fetchFile(path, { limit, signal })).bytes;
}

// A body's bytes, into one buffer of `length` where it is known (no copy but the one
// from each piece), else gathered and joined; more than `limit` bytes is TooLarge.
async function readBody(reader, name, length, limit) {
  const out = length == null ? null : new Uint8Array(length);
  const pieces = [];
  let at = 0;
  try {
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      if (at + value.byteLength > (length ?? limit)) {
        throw length == null ? new TooLarge(name, null, limit) : new Error(`${name} sent more than the ${length} bytes it announced`);
      }
      if (out) out.set(value, at);
      else pieces.push(value);
      at += value.byteLength;
    }
  } catch (e) {
    reader.cancel().catch(() => {});
    throw e;
  }
  if (out) {
    if (at !== length) throw new Error(`${name} was cut short: ${at} of ${length} bytes came`);
    return out.buffer;
  }
  const joined = new Uint8Array(at);
  let to = 0;
  for (const p of pieces) {
    joined.set(p, to);
    to += p.byteLength;
  }
  return joined.buffer;
}

// A banner; one about a run (`run` set) clears when another run is selected.
let bannerRun = null;
function banner(text, kind = 'error', run = null) {
  const b = $('banner');
  b.textContent = text;
  b.className = kind;
  b.hidden = !text;
  bannerRun = run;
}

// ---------------------------------------------------------------- formatting

const fmtS = (s) => (s == null ? '–' : s < 90 ? `${s.toFixed(1)} s` : s < 5400 ? `${(s / 60).toFixed(1)} min` : `${(s / 3600).toFixed(1)} h`);
const fmtBytes = (b) => (b >= 2 ** 30 ? `${(b / 2 ** 30).toFixed(2)} GiB` : b >= 2 ** 20 ? `${(b / 2 ** 20).toFixed(1)} MiB` : `${(b / 1024).toFixed(0)} KiB`);
const deg = (a) => `${((a.x * 180) / Math.PI).toFixed(2)}°, ${((a.y * 180) / Math.PI).toFixed(2)}°`;

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === 'class') e.className = v;
    else if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}

// Viridis, from 8 of its stops.
const VIRIDIS = [[68, 1, 84], [70, 50, 127], [54, 92, 141], [39, 127, 142], [31, 161, 135], [74, 194, 109], [159, 218, 58], [253, 231, 37]];
const INFERNO = [[0, 0, 4], [40, 11, 84], [101, 21, 110], [159, 42, 99], [212, 72, 66], [245, 125, 21], [250, 193, 39], [252, 255, 164]];
function cmap(stops, t) {
  if (!(t >= 0)) t = 0;
  if (t > 1) t = 1;
  const x = t * (stops.length - 1);
  const i = Math.min(stops.length - 2, Math.floor(x));
  const f = x - i;
  return stops[i].map((c, k) => Math.round(c + (stops[i + 1][k] - c) * f));
}
const css = (rgb) => `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`;

// The smallest and largest of `values`, by a loop: spreading an array into Math.min
// passes each element as an argument, and throws past about 125,000. [Infinity,
// -Infinity] for none.
function extent(values) {
  let lo = Infinity;
  let hi = -Infinity;
  for (const v of values) {
    if (v < lo) lo = v;
    if (v > hi) hi = v;
  }
  return [lo, hi];
}

// ---------------------------------------------------------------- instrument panel

let instrumentFetched = 0;
let instrument = null;
// The running run's latest histogram: arm angles and count rate while it holds the devices.
let liveReading = null;

function renderInstrument() {
  const body = $('inst-body');
  if (!instrument) return;
  const v = instrument;
  $('inst-name').textContent = v.name;
  const rows = [];
  const row = (k, val, cls = '') => rows.push(el('tr', {}, el('th', {}, k), el('td', { class: cls }, val)));
  row('instrument', v.summary);
  row('state', v.busy ? `busy: run ${v.run?.id} (${v.run?.stage})` : 'idle');
  const d = v.devices;
  if (d) {
    // While a run holds the devices, this reading is from before it started.
    const before = v.busy ? ' (read before the run)' : '';
    if (v.busy) {
      // A reading from before the run says nothing of the laser now: the bar at the
      // top shows the run's own readings.
      row('laser, interlock, diffuser', 'live in the safety bar at the top (the run reads them at every pair)');
    } else {
      // A reading past its age limit says nothing of now: unknown, never a green off.
      const readAge = v.reading ? v.reading.age_s + (performance.now() - instrumentFetched) / 1000 : Infinity;
      if (!(readAge <= (v.reading?.stale_after_s ?? 0))) {
        const why = v.reading ? `unknown: the reading is ${fmtS(readAge)} old` : 'unknown: not read';
        for (const k of ['laser', 'interlock', 'diffuser']) row(k, why, 'warn');
      } else {
        row('laser', d.laser.emission ? 'ON' : 'off', d.laser.emission ? 'danger' : 'ok');
        row('interlock', d.laser.interlock_closed ? 'closed' : 'OPEN', d.laser.interlock_closed ? 'ok' : 'danger');
        row('diffuser', d.laser.diffuser_in ? 'in' : 'out');
      }
    }
    row('laser arm', `${d.laser_arm.model} ${d.laser_arm.firmware} at (${deg(d.laser_position)})${before}`);
    row('SPAD arm', `${d.spad_arm.model} ${d.spad_arm.firmware} at (${deg(d.spad_position)})${before}`);
    row('histogrammer', `${d.tdc.model} ${d.tdc.firmware}: ${JSON.stringify(d.tdc_status.state)}${before}`);
    const rates = d.tdc_status.rates || {};
    row('count rates', (Object.entries(rates).map(([k, r]) => `${k} ${Number(r).toLocaleString()} /s`).join(' · ') || '–') + before);
  }
  const lr = liveReading;
  if (v.busy && lr && lr.run === v.run?.id) {
    const age = (performance.now() - lr.at) / 1000;
    row('live (from the run)', `laser arm at (${lr.laser[0].toFixed(2)}°, ${lr.laser[1].toFixed(2)}°), SPAD arm at (${lr.spad[0].toFixed(2)}°, ${lr.spad[1].toFixed(2)}°)`);
    row('live signal', `${Math.round(lr.rate).toLocaleString()} counts/s on pair ${lr.pair}, ${fmtS(age)} ago`, age > 30 ? 'warn' : '');
  }
  if (v.error) row('devices', v.error, 'danger');
  if (v.note) row('note', v.note);
  if (v.last_safe) row('last safe state', v.last_safe);
  const age = v.reading ? v.reading.age_s + (performance.now() - instrumentFetched) / 1000 : null;
  row('reading age', age == null ? 'not read yet' : fmtS(age), age != null && age > 30 ? 'warn' : '');
  body.replaceChildren(el('table', { class: 'kv' }, ...rows));
}

async function pollInstrument() {
  const sentAt = performance.now();
  try {
    instrument = await api('GET', '/api/v1/instrument', undefined, POLL_TIMEOUT_MS);
    instrumentFetched = performance.now();
    renderInstrument();
    setConnection(true);
  } catch (e) {
    if (e.name === 'AbortError') return;
    if (e instanceof TypeError || e.name === 'TimeoutError') {
      const silent = e.name === 'TimeoutError';
      if (silent) pollTimedOut(sentAt);
      else setConnection(false);
      // An old reading must not pass for a current one.
      instrument = null;
      $('inst-body').textContent = `The daemon ${silent ? `has not answered for ${POLL_TIMEOUT_MS / 1000} s` : 'cannot be reached'}: nothing here is current. In doubt, use the hardware emergency stop.`;
    } else {
      instrument = null;
      $('inst-body').textContent = e.message;
    }
  }
}

const NOT_ANSWERING = `daemon not answering (nothing in ${POLL_TIMEOUT_MS / 1000} s): retrying`;
function setConnection(up, why = 'daemon unreachable: retrying') {
  const c = $('conn');
  c.textContent = up ? 'connected' : why;
  c.className = `pill ${up ? 'ok' : 'danger'}`;
  probe.connection = c.textContent;
}

// A poll sent at `sentAt` got no answer in POLL_TIMEOUT_MS. The pill says so, and so
// does the E-STOP's label at once: the polls go one after another, each waiting up to
// 6 s, and the label must not read "armed" until the caller check's turn comes round.
// Unless the daemon has answered another request since this one went out: then this
// silence is its connection's (one dropped without a close), not the daemon's, and
// the label waits for its own check.
function pollTimedOut(sentAt) {
  setConnection(false, NOT_ANSWERING);
  if (answeredAt > sentAt) return;
  estopNotAnswering();
}

// The E-STOP's label when the daemon does not answer.
function estopNotAnswering() {
  const st = $('estop-state');
  st.textContent = `DAEMON NOT ANSWERING (nothing in ${POLL_TIMEOUT_MS / 1000} s): use the hardware emergency stop`;
  st.className = 'estop-state unreachable';
  probe.estop = 'unreachable';
}

// Whether the E-STOP will work from this page: from this computer it needs no key; from
// another, any valid key. Shown under the button, checked at every refresh.
let caller = null; // { name, role } from GET /api/v1/whoami

async function checkEstop() {
  const st = $('estop-state');
  try {
    const r = await pageFetch('/api/v1/whoami', { headers: headers() }, POLL_TIMEOUT_MS);
    if (r.ok) {
      caller = await r.json();
      st.textContent = caller.name === 'loopback' ? 'armed: works from this computer without a key' : `armed: key ${caller.name} (${caller.role})`;
      st.className = 'estop-state armed';
    } else if (r.status === 401 || r.status === 403) {
      caller = null;
      st.textContent = 'NOT armed from this machine: enter a key (any role) to e-stop from here';
      st.className = 'estop-state disarmed';
    } else {
      // Busy (503), timed out on its side (408), or anything else: the key may be
      // fine, but whether the E-STOP would be heard is not known.
      caller = null;
      st.textContent = `E-STOP state unknown: the daemon answered ${r.status}${r.statusText ? ` ${r.statusText}` : ''}; in doubt, use the hardware emergency stop`;
      st.className = 'estop-state unknown';
    }
  } catch (e) {
    if (e.name === 'AbortError') return;
    caller = null;
    if (e.name === 'TimeoutError') {
      estopNotAnswering();
    } else {
      st.textContent = 'DAEMON UNREACHABLE: use the hardware emergency stop';
      st.className = 'estop-state unreachable';
    }
  }
  probe.estop = st.className.replace('estop-state ', '');
  updateSubmit();
}

// How long the E-STOP waits for the daemon's answer before it tells the operator to
// use the hardware one; it goes on waiting for the report, which the daemon may take
// up to 10 s to give (it waits up to 2 s for a run to park, then parks the arms
// itself), and shows it when it comes.
const ESTOP_HINT_MS = 3000;
const ESTOP_TIMEOUT_MS = 11000;

// The E-STOP's report has a place of its own, which nothing else on the page writes:
// a failure stays in view until the operator dismisses it or presses again.
function estopReport(text, kind = 'error') {
  $('estop-text').textContent = text;
  $('estop-report').className = kind;
  $('estop-report').hidden = !text;
  probe.estopReport = text;
}
$('estop-dismiss').addEventListener('click', () => estopReport(''));

$('estop').addEventListener('click', async () => {
  const t0 = performance.now();
  // Whatever the page is waiting for gives its connection to the E-STOP.
  cancelPageRequests();
  probe.cancelledForEstop = (probe.cancelledForEstop || 0) + 1;
  estopReport('E-STOP sent…');
  const hint = setTimeout(() => {
    estopReport(`E-STOP: no answer after ${ESTOP_HINT_MS / 1000} s: press the HARDWARE emergency stop on the laser controller now (still waiting for the daemon's report)`);
  }, ESTOP_HINT_MS);
  try {
    const resp = await fetch('/api/v1/estop', { method: 'POST', headers: headers(), signal: AbortSignal.timeout(ESTOP_TIMEOUT_MS) });
    const r = await resp.json().catch(() => null);
    if (!resp.ok || !r) throw new ApiError(resp.status, r?.error, r?.message || `${resp.status} ${resp.statusText}`);
    const parts = [`E-STOP done in ${((performance.now() - t0) / 1000).toFixed(2)} s: ${r.laser}`];
    if (r.aborted) parts.push(`run ${r.aborted} aborted`);
    parts.push(r.parked ? 'arms parked' : 'arms NOT parked');
    if (r.held?.length) parts.push(`held: ${r.held.join(', ')}`);
    if (r.warnings?.length) parts.push(`warnings: ${r.warnings.join('; ')}`);
        // Green only when the laser is confirmed off and the arms parked.
    const laserOff = typeof r.laser === 'string' && r.laser.startsWith('off');
    estopReport(parts.join(' · '), laserOff && r.parked ? 'notice' : 'error');
  } catch (e) {
    if (e.name === 'TimeoutError') {
      estopReport(`E-STOP got no answer within ${ESTOP_TIMEOUT_MS / 1000} s: press the HARDWARE emergency stop on the laser controller now.`);
    } else if (e instanceof TypeError) {
      estopReport('E-STOP could not reach the daemon: press the HARDWARE emergency stop on the laser controller now.');
    } else {
      estopReport(`E-STOP refused (${e.message}): press the HARDWARE emergency stop on the laser controller now.`);
    }
  } finally {
    clearTimeout(hint);
  }
  refresh();
});

// ---------------------------------------------------------------- plan editor

let checkedText = null;
let checkTimer = null;

// Until a loaded plan is checked, nothing about the old one stays on screen.
function planLoading() {
  checkedText = null;
  planOk = false;
  updateSubmit();
  $('check-summary').textContent = 'loading…';
}

$('load-demo').addEventListener('click', async () => {
  planLoading();
  try {
    // Through `pageFetch`, so the E-STOP can take its connection as it takes the polls'.
    const text = await pageFetch('/ui/plans/demo.toml', {}, null, async (r) => {
      if (!r.ok) {
        const json = await jsonBody(r);
        throw new ApiError(r.status, json?.error, json?.message || `${r.status} ${r.statusText}`);
      }
      return r.text();
    });
    $('plan').value = text;
    planEdited();
  } catch (e) {
    // The editor keeps what it held, unchecked: Check (or an edit) checks it.
    const why = e.name === 'AbortError' ? 'cancelled by the E-STOP: press it again'
      : e instanceof TypeError ? 'the daemon could not be reached' : e.message;
    $('check-summary').replaceChildren(el('span', { class: 'danger' }, `the demo plan could not be loaded: ${why}`));
  }
});

$('plan-file').addEventListener('change', async (e) => {
  const f = e.target.files[0];
  if (!f) return;
  planLoading();
  $('plan').value = await f.text();
  planEdited();
});

// Line numbers beside the plan, the offending line marked.
let errorLine = null;
function drawLines() {
  const n = $('plan').value.split('\n').length;
  const out = [];
  for (let i = 1; i <= n; i++) out.push(i === errorLine ? `<span class="err">${i}</span>` : String(i));
  $('plan-lines').innerHTML = out.join('\n');
}
$('plan').addEventListener('scroll', () => {
  $('plan-lines').style.transform = `translateY(${-$('plan').scrollTop}px)`;
});

function showProblem(message) {
  const m = /(?:request body|plan\.toml|batch plan \d+):(\d+):/.exec(message || '');
  errorLine = m ? Number(m[1]) : null;
  drawLines();
  const p = $('check-problem');
  p.hidden = !message;
  p.textContent = message ? (errorLine ? `line ${errorLine}: ${message}` : message) : '';
  probe.errorLine = errorLine;
}

function showWarnings(items) {
  const w = $('check-warnings');
  w.hidden = !items.length;
  w.replaceChildren(...items.map((t) => el('div', {}, `⚠ ${t}`)));
}

// Submit is enabled only when it can succeed: a checked plan within budget, a key
// that may submit, an unlocked queue. Otherwise the reason is shown beside it.
let planOk = false;
let queueLock = null;
function updateSubmit() {
  const why = [];
  if (!planOk) why.push('check the plan first (it must be valid and within budget)');
  if (!caller) why.push('the daemon cannot be reached or does not know this page');
  else if (!['operator', 'admin'].includes(caller.role)) why.push(token ? `key role ${caller.role} may not submit` : 'enter an operator key to submit');
  if (queueLock) why.push(`the queue is locked by ${queueLock.by}: ${queueLock.reason}`);
  $('submit').disabled = why.length > 0;
  $('submit').title = why.join('; ') || 'queue this plan';
  $('submit-why').textContent = why.length ? `submit: ${why.join('; ')}` : '';
  updateImport();
}

// ---------------------------------------------------------------- imports

// Import is enabled when a capture file is chosen, the key may submit and the queue
// is unlocked, and no import is uploading from this page.
let importing = false;
function updateImport() {
  const why = [];
  if (!$('import-file').files.length) why.push('choose a capture file');
  if (!caller) why.push('the daemon cannot be reached or does not know this page');
  else if (!['operator', 'admin'].includes(caller.role)) why.push(token ? `key role ${caller.role} may not import` : 'enter an operator key to import');
  if (queueLock) why.push(`the queue is locked by ${queueLock.by}: ${queueLock.reason}`);
  if (importing) why.push('an import is uploading');
  $('import-go').disabled = why.length > 0;
  $('import-go').title = why.join('; ') || 'upload the file and queue its reconstruction';
  $('import-why').textContent = why.length && $('import-file').files.length ? `import: ${why.join('; ')}` : '';
}
$('import-file').addEventListener('change', updateImport);

// The method menu writes the settings' `method` line, so the settings are the one
// place the reconstruction is described.
$('import-method').addEventListener('change', () => {
  const m = $('import-method').value;
  const lines = $('import-recon').value.split('\n').filter((l) => !/^\s*method\s*=/.test(l));
  if (m) lines.unshift(`method = "${m}"`);
  $('import-recon').value = lines.join('\n').trim() + (lines.some((l) => l.trim()) ? '\n' : '');
});

// Uploads with XMLHttpRequest, which reports the upload's progress (fetch does not).
// The E-STOP cancels an upload as it cancels the polls (`inflight`): it holds a
// connection the E-STOP may need.
function uploadForm(path, form, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    const ctl = { abort: () => xhr.abort() };
    inflight.add(ctl);
    xhr.onloadend = () => inflight.delete(ctl);
    xhr.onabort = () => reject(new DOMException('cancelled for the E-STOP', 'AbortError'));
    xhr.open('POST', path);
    // The key this upload goes out with, for its 401 (`unauthorized`).
    const sent = token;
    if (token) xhr.setRequestHeader('Authorization', `Bearer ${token}`);
    xhr.upload.onprogress = (e) => { if (e.lengthComputable) onProgress(e.loaded / e.total); };
    xhr.onload = () => {
      let json = null;
      try { json = JSON.parse(xhr.responseText); } catch { json = null; }
      if (xhr.status >= 200 && xhr.status < 300) resolve(json);
      else reject(refusal(xhr, json, sent));
    };
    xhr.onerror = () => reject(new ApiError(0, null, 'the daemon could not be reached'));
    xhr.send(form);
  });
}

$('import-go').addEventListener('click', async () => {
  const file = $('import-file').files[0];
  if (!file) return;
  const form = new FormData();
  form.append('capture', file, file.name);
  for (const f of $('import-sidecars').files) form.append('sidecar', f, f.name);
  const recon = $('import-recon').value;
  if (recon.trim()) form.append('recon', recon);
  const name = $('import-name').value.trim();
  if (name) form.append('name', name);
  importing = true;
  updateImport();
  const progress = $('import-progress');
  progress.hidden = false;
  progress.value = 0;
  $('import-status').textContent = `uploading ${file.name} (${fmtBytes(file.size)})…`;
  try {
    const st = await uploadForm('/api/v1/imports', form, (f) => { progress.value = f; });
    $('import-status').textContent = `imported as run ${st.id}`;
    await refreshRuns();
    select(st.id);
    banner(`${file.name} imported: run ${st.id} queued`, 'notice', st.id);
  } catch (e) {
    if (e.name === 'AbortError') {
      // The file may have reached the daemon before the cancel: the runs list says.
      $('import-status').textContent = `upload of ${file.name} cancelled by the E-STOP: check the runs list before importing it again`;
      probe.importCancelled = (probe.importCancelled || 0) + 1;
    } else {
      $('import-status').textContent = '';
      banner(`import refused: ${e.message}`);
    }
  } finally {
    importing = false;
    progress.hidden = true;
    updateImport();
  }
});

function planEdited() {
  checkedText = null;
  planOk = false;
  errorLine = null;
  drawLines();
  $('submit').disabled = true;
  $('check-summary').textContent = 'checking…';
  clearTimeout(checkTimer);
  checkTimer = setTimeout(checkPlan, 600);
}
$('plan').addEventListener('input', planEdited);
$('check').addEventListener('click', checkPlan);

async function checkPlan() {
  clearTimeout(checkTimer);
  const text = $('plan').value;
  const out = $('check-out');
  const summary = $('check-summary');
  if (!text.trim()) {
    summary.textContent = '';
    out.textContent = '';
    return;
  }
  // Whether the daemon's report came (a refusal throws before this is set).
  let answered = false;
  try {
    const c = await api('POST', '/api/v1/check', text);
    answered = true;
    if ($('plan').value !== text) return;
    out.textContent = c.report;
    const d = c.duration_s;
    summary.replaceChildren(
      el('span', { class: c.over_budget ? 'danger' : 'ok' }, c.over_budget ? 'over budget' : 'valid'),
      ` · plan “${c.plan}” · ${c.pairs.toLocaleString()} pairs · about ${fmtS(d.total)} (LOS ${fmtS(d.los)}, capture ${fmtS(d.capture)}, reconstruction ${fmtS(d.reconstruction)})`,
      ` · memory ${fmtBytes(c.memory_bytes)} of ${fmtBytes(c.memory_limit)} · disk ${fmtBytes(c.disk_bytes)} of ${fmtBytes(c.disk_limit)}`,
    );
    showProblem(c.over_budget ? `over the run budget: ${c.over_budget}` : null);
    const warnings = [];
    if (c.problems.length) {
      warnings.push(`${c.problems.length} target(s) outside the galvo limits (they are skipped): ${c.problems.slice(0, 3).join('; ')}${c.problems.length > 3 ? ' …' : ''}`);
    }
    for (const w of c.warnings || []) warnings.push(w);
    const near = (used, limit) => limit > 0 && used > 0.8 * limit && used <= limit;
    if (near(c.memory_bytes, c.memory_limit)) warnings.push(`memory ${fmtBytes(c.memory_bytes)} is over 80 % of the budget ${fmtBytes(c.memory_limit)}`);
    if (near(c.disk_bytes, c.disk_limit)) warnings.push(`disk ${fmtBytes(c.disk_bytes)} is over 80 % of the budget ${fmtBytes(c.disk_limit)}`);
    showWarnings(warnings);
    if (c.over_budget) out.textContent = `${c.over_budget}\n\n${c.report}`;
    checkedText = c.over_budget ? null : text;
    planOk = checkedText !== null;
    updateSubmit();
  } catch (e) {
    if ($('plan').value !== text) return;
    // A verdict on the plan is a 422 (`invalid-plan`) or a 413 (a plan over the body
    // limit); anything else (a 401 key, a 403 role, a 429 or 503 of a busy daemon)
    // says nothing of the plan.
    const verdict = e instanceof ApiError && (e.status === 422 || e.status === 413);
    if (!verdict && !answered) {
      // No verdict on the plan: the check was cancelled (the E-STOP takes the page's
      // connections), never reached the daemon, or was refused for something else.
      // The plan is left unchecked, not called invalid, and Check asks again. A plan
      // checked valid before keeps that.
      const why = givenUp(e) ? 'the check was cancelled by the E-STOP'
        : e instanceof ApiError ? `the daemon did not check it: ${e.message}`
          : 'the daemon could not be reached';
      summary.replaceChildren(el('span', { class: 'warn' }, `not checked: ${why}; press check`));
      planOk = checkedText === text;
      updateSubmit();
      return;
    }
    summary.replaceChildren(el('span', { class: 'danger' }, 'invalid'));
    out.textContent = e.message;
    showProblem(e.message);
    showWarnings([]);
    planOk = false;
    updateSubmit();
  }
}

$('submit').addEventListener('click', async () => {
  const text = $('plan').value;
  if (text !== checkedText) return;
  $('submit').disabled = true;
  // Whether the daemon answered the submission (a refusal is an answer).
  let answered = false;
  try {
    const st = await api('POST', '/api/v1/runs', text);
    answered = true;
    await refreshRuns();
    select(st.id);
    banner(`run ${st.id} queued`, 'notice', st.id);
  } catch (e) {
    if (!answered && e.name === 'AbortError') {
      // Not a refusal: the plan may have reached the daemon before the cancel (its run
      // then held by the e-stop), as an import's upload may.
      banner('submit cancelled by the E-STOP: check the runs list before submitting the plan again');
      probe.submitCancelled = (probe.submitCancelled || 0) + 1;
    } else if (!answered && e instanceof TypeError) {
      banner('submit failed: the daemon could not be reached (check the runs list before submitting the plan again)');
    } else {
      banner(`submit refused: ${e.message}`);
    }
  } finally {
    updateSubmit();
  }
});

// ---------------------------------------------------------------- runs

let runs = [];
let selected = null;

async function action(id, verb) {
  try {
    await api('POST', `/api/v1/runs/${id}/${verb}`);
  } catch (e) {
    if (e.name === 'AbortError') {
      // Not a refusal: the request may have reached the daemon before the cancel.
      banner(`${verb} of run ${id} cancelled by the E-STOP: check the runs list`);
    } else if (e instanceof TypeError) {
      banner(`${verb} of run ${id} failed: the daemon could not be reached (check the runs list)`);
    } else {
      banner(`${verb} refused: ${e.message}`);
    }
  }
  await refreshRuns();
}

// Abort cannot be undone, and the runs table is rebuilt as runs change state (a row
// can move under the pointer between aiming and clicking): the operator confirms it,
// the run named.
function confirmAbort(r) {
  const what = `run ${r.id}${r.plan ? ` (plan “${r.plan}”)` : ''}, now ${r.state}`;
  if (window.confirm(`Abort ${what}? Its captured pairs are kept, but it cannot be resumed.`)) action(r.id, 'abort');
}

function actionButtons(r) {
  const buttons = [];
  if (r.state === 'running') buttons.push(el('button', { class: 'act-pause', onclick: () => action(r.id, 'pause') }, 'pause'));
  if (r.state === 'paused' || r.state === 'failed') buttons.push(el('button', { class: 'act-resume', onclick: () => action(r.id, 'resume') }, 'resume'));
  if (['queued', 'running', 'paused', 'failed'].includes(r.state)) buttons.push(el('button', { class: 'act-abort', title: `abort run ${r.id} (asks first)`, onclick: () => confirmAbort(r) }, 'abort'));
  return buttons;
}

let runsRendered = '';

function renderRuns() {
  // Rebuilt only when something shown changed, so clicks land on live buttons.
  const key = JSON.stringify([selected, runs.map((r) => [r.id, r.state, r.stage, Math.round(r.progress * 100), r.timings.length, r.queue_position])]);
  if (key === runsRendered) return;
  runsRendered = key;
  const rows = [...runs].reverse().map((r) => {
    const timings = r.timings.map(([s, t]) => `${s} ${fmtS(t)}`).join(' · ');
    const tr = el('tr', { class: r.id === selected ? 'selected' : '', 'data-run': r.id },
      el('td', {}, el('a', { href: `#${r.id}`, onclick: (e) => { e.preventDefault(); select(r.id); } }, r.id)),
      el('td', {}, r.plan, r.imported ? el('span', { class: 'small', title: `imported capture ${r.imported}` }, ` · imported ${r.imported}`) : ''),
      el('td', { class: `state-${r.state}` }, r.state + (r.queue_position != null ? ` (#${r.queue_position + 1})` : '')),
      el('td', {}, r.stage),
      el('td', {}, `${Math.round(r.progress * 100)} %`),
      el('td', { class: 'small' }, timings),
      el('td', {}, ...actionButtons(r)));
    return tr;
  });
  $('runs-body').replaceChildren(...rows);
  if (!runs.length) $('runs-body').append(el('tr', {}, el('td', { colspan: 7 }, 'no runs yet')));
}

/// The runs table's query: the newest 100 matching runs from the run catalogue.
function runsQuery() {
  const p = new URLSearchParams({ order: 'desc', limit: '100' });
  const q = $('runs-filter').value.trim();
  const state = $('runs-state').value;
  if (q) p.set('q', q);
  if (state) p.set('state', state);
  return `/api/v1/runs?${p}`;
}

let runsAsked = 0;
let runsInFlight = null;
let runsAgain = false;
// One runs request at a time: a keystroke in the filter (or a run's planning) while
// one is under way asks again once it is in, with the filter as it is then, so typing
// holds one connection, not one a keystroke.
async function refreshRuns() {
  if (runsInFlight) {
    runsAgain = true;
    return runsInFlight;
  }
  runsInFlight = (async () => {
    do {
      runsAgain = false;
      await fetchRuns();
    } while (runsAgain);
  })();
  try {
    await runsInFlight;
  } finally {
    runsInFlight = null;
  }
}

// Why the runs list shown is not the answer to the filter as it is (empty: it is),
// beside the filter.
function runsProblem(text) {
  $('runs-problem').textContent = text;
  $('runs-problem').hidden = !text;
  probe.runsProblem = text;
}

async function fetchRuns() {
  const asked = ++runsAsked;
  // The key this request goes out with, for its 401 (`unauthorized`).
  const sent = token;
  const sentAt = performance.now();
  try {
    const r = await pageFetch(runsQuery(), { headers: headers({}) }, POLL_TIMEOUT_MS);
    // A refusal (400 `bad-query`: a search over 128 bytes; a 500 from the catalogue)
    // is said beside the filter, in the daemon's words, and a 401 asks for the key as
    // every other request does.
    if (!r.ok) throw refusal(r, await jsonBody(r), sent);
    const total = r.headers.get('x-total-count');
    const list = (await r.json()).reverse();
    // An answer to an older query (the filter changed since) is dropped.
    if (asked !== runsAsked) return;
    // Oldest first, as the rest of the page expects.
    runs = list;
    $('runs-count').textContent = total != null ? `${runs.length} of ${total}` : '';
    runsProblem('');
    setConnection(true);
  } catch (e) {
    if (e instanceof TypeError) setConnection(false);
    else if (e.name === 'TimeoutError') pollTimedOut(sentAt);
    else if (e instanceof ApiError && asked === runsAsked) runsProblem(`runs not updated (the list below is the last one read): ${e.message}`);
    return;
  }
  renderRuns();
  if (!selected) {
    const active = [...runs].reverse().find((r) => r.state === 'running') || runs[runs.length - 1];
    if (active) select(active.id);
  } else {
    const r = runs.find((x) => x.id === selected);
    if (r) onStatus(r);
  }
}

// ---------------------------------------------------------------- the audit trail

let auditRendered = '';

async function refreshAudit() {
  if (document.hidden) return;
  const sentAt = performance.now();
  let page;
  try {
    page = await api('GET', '/api/v1/audit?limit=20', undefined, POLL_TIMEOUT_MS);
  } catch (e) {
    if (e.name === 'TimeoutError') pollTimedOut(sentAt);
    return;
  }
  const key = JSON.stringify(page.entries.map((e) => e.id));
  if (key === auditRendered) return;
  auditRendered = key;
  const rows = page.entries.map((e) => el('tr', { class: e.outcome === 'ok' ? '' : 'audit-refused' },
    el('td', { class: 'small' }, new Date(e.at_unix_s * 1000).toISOString().slice(0, 19).replace('T', ' ')),
    el('td', {}, e.actor),
    el('td', {}, e.role),
    el('td', {}, e.action),
    el('td', { class: 'small' }, e.target || ''),
    el('td', { class: e.outcome === 'ok' ? '' : 'state-failed' }, e.outcome),
    el('td', { class: 'small' }, e.detail || '')));
  $('audit-body').replaceChildren(...rows);
  if (!rows.length) $('audit-body').append(el('tr', {}, el('td', { colspan: 7 }, 'nothing recorded yet')));
}

// ---------------------------------------------------------------- the selected run

const view = new View3D($('view3d'));
let histPlot = null;
let lossPlot = null;
let lossSteps = new Map();
// An adaptive capture's choices, by batch (replayed events may repeat one).
let chosenBatches = new Map();
let live = null; // { id, abort: AbortController }
let status = null;
let statusAt = 0;
let geometryStage = null;
let resultsFor = null;
// The selected run's loads (its event log, geometry, results and volume) are
// cancelled when another run is chosen: files of a run no longer shown must not hold
// the browser's connections, nor the daemon's download slots (503
// `too-many-downloads`), while the new run's files load.
let selection = new AbortController();

// A load that failed for a reason that may pass (the daemon busy: 503
// `too-many-downloads`; no answer; a 500) is tried again at a poll, first after
// RETRY_MIN_MS, then twice as long each time up to RETRY_MAX_MS, so a failing file is
// not asked for every 2 s. The page's own failure to read a file it got is not
// retried (it would fail again); choosing the run again starts afresh.
const RETRY_MIN_MS = 5000;
const RETRY_MAX_MS = 60000;
const retryDelay = (failures) => Math.min(RETRY_MIN_MS * 2 ** failures, RETRY_MAX_MS);
const mayPass = (e) => givenUp(e) || e instanceof TypeError || e instanceof ApiError;
// The results' (volume.json and depth.npy) failed tries, and when to try again.
let resultsFailures = 0;
let resultsRetryAt = 0;
// The volume's failed tries, and the timer that tries again.
let volumeFailures = 0;
let volumeRetry = null;

// A suspender holding the selected run (its `suspended` event: `reason`, `resume`),
// until its `suspend-cleared`, a measured pair, or the run no longer running; and
// when a live event last set it (`loadHistory` does not undo what the stream said
// after its request went out).
let suspension = null;
let suspensionLiveAt = -Infinity;

// How much of the selected run's events.jsonl the page has read: `offset`, the byte
// just past the last whole line taken (a line still being written is read again with
// what follows it); `failures` and `retryAt` for a read that failed (Infinity: none
// waiting).
let eventLog = { id: null, offset: 0, failures: 0, retryAt: Infinity };

function makePlots() {
  histPlot?.destroy();
  lossPlot?.destroy();
  const hist = $('hist-plot');
  const loss = $('loss-plot');
  hist.replaceChildren();
  loss.replaceChildren();
  const width = Math.max(280, hist.clientWidth || 400);
  histPlot = new uPlot({
    width, height: 220,
    scales: { x: { time: false } },
    axes: [{ label: 'time after the pulse (ns)' }, { label: 'counts', size: 60 }],
    series: [{}, { label: 'counts', stroke: '#2a7ab9', fill: 'rgba(42,122,185,0.15)', points: { show: false } }],
    legend: { show: false },
  }, [[], []], hist);
  lossPlot = new uPlot({
    width, height: 220,
    scales: { x: { time: false }, y: { distr: 3 } },
    axes: [{ label: 'optimiser step' }, { label: 'loss', size: 70 }],
    series: [{}, { label: 'loss', stroke: '#c0392b', points: { show: true, size: 4 } }],
    legend: { show: false },
  }, [[], []], loss);
}

function select(id) {
  if (selected === id && live) return;
  selected = id;
  if (live) live.abort.abort();
  live = null;
  // The last run's loads still under way are cancelled (their connections and the
  // daemon's download slots are the new run's), and its volume waits no more to be
  // scrolled into view.
  selection.abort();
  selection = new AbortController();
  resultsObserver?.disconnect();
  clearTimeout(volumeRetry);
  volumeRetry = null;
  status = null;
  geometryStage = null;
  resultsFor = null;
  resultsFailures = 0;
  resultsRetryAt = 0;
  volumeFailures = 0;
  suspension = null;
  suspensionLiveAt = -Infinity;
  eventLog = { id, offset: 0, failures: 0, retryAt: Infinity };
  lossSteps = new Map();
  chosenBatches = new Map();
  makePlots();
  view.clear();
  $('hist-caption').textContent = 'no histogram yet';
  $('run-id').textContent = id;
  // Everything shown belongs to the selected run: nothing of the last one stays.
  $('results-body').hidden = true;
  $('results-note').textContent = 'results appear when the run completes';
  $('downloads').replaceChildren();
  $('view-caption').textContent = '';
  $('gauss-caption').textContent = '';
  $('chosen-caption').textContent = '';
  $('view-colourbar').hidden = true;
  $('run-error').textContent = '';
  for (const c of ['depth-canvas', 'albedo-canvas', 'mip-x', 'mip-y', 'mip-z', 'slice-canvas']) $(c).width = 0;
  for (const f of ['run-state', 'run-stage', 'run-pairs', 'run-eta', 'run-loss']) $(f).textContent = '';
  $('run-progress').value = 0;
  $('run-actions').replaceChildren();
  $('run-actions').dataset.key = '';
  downloadsKey = null;
  volume = null;
  // The last choice's array work is of no use now: stop it rather than wait for it.
  if (jobs.size) stopWorker(Object.assign(new Error(`run ${id} was chosen`), { name: 'Superseded' }));
  if (bannerRun && bannerRun !== id) banner('');
  renderRuns();
  loadHistory(id);
  const r = runs.find((x) => x.id === id);
  if (r) onStatus(r);
  follow(id);
}

function onStatus(st) {
  if (st.id !== selected) return;
  status = st;
  statusAt = performance.now();
  // A suspender holds a running run; one that stopped (paused by a suspender whose
  // `resume` is the operator's, aborted, e-stopped) shows its state and error instead.
  if (st.state !== 'running' && suspension) {
    suspension = null;
    suspensionLiveAt = performance.now();
  }
  renderSummary();
  // A run resumed or started after its page stopped following it: follow it again.
  if (['running', 'queued'].includes(st.state) && !live) follow(st.id);
  // The 3-D view: the relay after the relay stage, the pairs once planned.
  const stage = ['queued', 'opening', 'los-scan', 'starting'].includes(st.stage) ? 'none' : st.pairs_total > 0 ? 'planned' : 'relay';
  if (stage !== 'none' && stage !== geometryStage) {
    geometryStage = stage;
    loadGeometry(st.id);
  }
  renderDownloads(st);
  // The event log, read again once a failed read's wait is over.
  if (eventLog.id === st.id && performance.now() >= eventLog.retryAt) {
    eventLog.retryAt = Infinity;
    loadHistory(st.id);
  }
  // Results for any run that has them: completed, or stopped after its outputs (and
  // again after a failed load, once its wait is over).
  if (st.files.includes('volume.npy') && st.files.includes('depth.npy') && resultsFor !== st.id) {
    if (performance.now() >= resultsRetryAt) {
      resultsFor = st.id;
      loadResults(st.id);
    }
  } else if (!st.files.includes('volume.npy') && ['aborted', 'failed', 'paused'].includes(st.state)) {
    $('results-note').textContent = `run ${st.state} before it was reconstructed: its ${st.pairs_done.toLocaleString()} captured pairs are kept (download capture.hdf5 below, or reconstruct it offline with periscope recon)`;
  }
}

// The selected run's files, for any state; an unfinished run's capture so far is
// exported on request as capture.hdf5.
let downloadsKey = null;
function renderDownloads(st) {
  const files = [...st.files];
  if (!files.includes('capture.hdf5') && st.pairs_done > 0) files.push('capture.hdf5');
  const key = `${st.id}:${files.join(',')}`;
  if (key === downloadsKey) return;
  downloadsKey = key;
  const id = st.id;
  $('downloads').replaceChildren(...files.map((f) => el('button', {
    class: 'download',
    'data-run': id,
    onclick: async () => {
      try {
        const blob = new Blob([await fetchBytes(`/api/v1/runs/${id}/files/${f}`)]);
        const a = el('a', { href: URL.createObjectURL(blob), download: `${id}-${f}` });
        a.click();
        setTimeout(() => URL.revokeObjectURL(a.href), 60000);
      } catch (e) {
        banner(givenUp(e) ? `download of ${f} cancelled (for the E-STOP): press it again to download` : `download failed: ${e.message}`);
      }
    },
  }, f)));
}

function renderSummary() {
  const st = status;
  if (!st) return;
  const eta = st.eta_s == null ? null : Math.max(0, st.eta_s - (performance.now() - statusAt) / 1000);
  $('run-state').textContent = st.state;
  $('run-state').className = `state-${st.state}`;
  $('run-stage').textContent = st.stage;
  $('run-progress').value = st.progress;
  $('run-pairs').textContent = st.pairs_total ? `${st.pairs_done.toLocaleString()} / ${st.pairs_total.toLocaleString()} pairs` : '';
  // The ETA is the capture's: shown only while the capture runs.
  const capturing = st.state === 'running' && st.stage === 'capture';
  $('run-eta').textContent = capturing && eta != null && eta > 0.5 ? `capture ends in about ${fmtS(eta)}` : '';
  $('run-loss').textContent = st.loss == null ? '' : `${st.state === 'completed' ? 'final loss' : 'loss'} ${st.loss.toExponential(3)}`;
  // A suspender holding the run says why (the laser is off until it clears): with
  // `resume = "auto"` the run waits, running, with no error of its own.
  const held = suspension && st.state === 'running'
    ? `held, laser off: ${suspension.reason} (${suspension.resume === 'auto' ? 'it goes on by itself once that clears' : 'it pauses: resume it once that is dealt with'})`
    : '';
  $('run-error').textContent = [held, st.error].filter(Boolean).join(' · ');
  probe.suspended = held || null;
  // Buttons are rebuilt only when they change, so a click never lands on a replaced one.
  const key = `${st.id}:${st.state}`;
  if ($('run-actions').dataset.key !== key) {
    $('run-actions').dataset.key = key;
    $('run-actions').replaceChildren(...actionButtons(st));
  }
}

// Past optimiser steps, an adaptive capture's choices and a suspender's hold, from
// events.jsonl, so a page opened mid-run (or after a dropped stream, or a `lagged`
// event) shows the whole loss curve. The log is read on from where the last read
// ended (`Range: bytes=N-`, answered 206), not downloaded whole at every drop: a long
// run's log is megabytes. A daemon that sends the whole file instead (200) has it read
// from the start (steps and batches are keyed by number: a line read twice changes
// nothing); a log shorter than what was read (416 naming a smaller length) is read
// again whole. A failed read is tried again at a later status (`onStatus`).
async function loadHistory(id) {
  if (eventLog.id !== id) eventLog = { id, offset: 0, failures: 0, retryAt: Infinity };
  const log = eventLog;
  const signal = selection.signal;
  const path = `/api/v1/runs/${id}/files/events.jsonl`;
  // Lines the stream delivered before this moment are in the file this read gets (the
  // daemon writes each event's line before it sends it).
  const asked = performance.now();
  try {
    let got = await fetchFile(path, { from: log.offset, signal });
    if (got.pastEnd) {
      // Nothing past what was read: nothing new.
      if (got.length === got.from) {
        log.failures = 0;
        return;
      }
      log.offset = 0;
      got = await fetchFile(path, { signal });
    }
    if (log !== eventLog || id !== selected) return;
    const bytes = new Uint8Array(got.bytes);
    // Whole lines only: a line still being written is read with what follows it.
    const end = bytes.lastIndexOf(10);
    // What the lines say of a suspender: undefined where they say nothing.
    let held;
    if (end >= 0) {
      for (const line of new TextDecoder().decode(bytes.subarray(0, end + 1)).split('\n')) {
        // A measured pair, or a stage started (a session resumed after a suspender
        // paused the run, which says no `suspend-cleared`): no suspender held the run
        // after it (cheaply, without parsing every pair's line).
        if (line.includes('"event":"pair"') || line.includes('"event":"stage-started"')) {
          held = null;
          continue;
        }
        const suspender = line.includes('"event":"suspended"') || line.includes('"event":"suspend-cleared"');
        if (!suspender && !line.includes('"epoch"') && !line.includes('"pairs-chosen"')) continue;
        try {
          const e = JSON.parse(line);
          if (e.event === 'epoch') lossSteps.set(e.step, e.loss);
          if (e.event === 'pairs-chosen') chosenBatches.set(e.batch, e);
          if (e.event === 'suspended') held = { reason: e.reason, resume: e.resume };
          if (e.event === 'suspend-cleared') held = null;
        } catch {
          // A line cut short by a crash: skip it.
        }
      }
      log.offset = Math.max(log.offset, got.from + end + 1);
    }
    log.failures = 0;
    // The log's word on a suspender, unless the stream said something since this read
    // went out, or the run is not running (`onStatus`).
    if (held !== undefined && asked > suspensionLiveAt && (!status || status.state === 'running')) {
      suspension = held;
      renderSummary();
    }
    drawLoss();
    drawChosen();
  } catch (e) {
    // Another run chosen: nothing to say. No log yet (404: a queued run): its
    // stream brings the events. Otherwise ask again later.
    if (signal.aborted || log !== eventLog) return;
    if (e instanceof ApiError && e.status === 404) return;
    if (mayPass(e)) log.retryAt = performance.now() + retryDelay(log.failures++);
  }
}

function drawLoss() {
  const steps = [...lossSteps.keys()].sort((a, b) => a - b);
  lossPlot.setData([steps, steps.map((s) => lossSteps.get(s))]);
  probe.lossPoints = steps.length;
}

let geometryRetry = null;
async function loadGeometry(id) {
  clearTimeout(geometryRetry);
  const signal = selection.signal;
  try {
    const g = await api('GET', `/api/v1/runs/${id}/geometry`, undefined, null, signal);
    if (id !== selected) return;
    // Planned but the pairs not stored yet: ask again shortly.
    if (status?.pairs_total > 0 && g.illumination.length === 0) {
      geometryRetry = setTimeout(() => id === selected && loadGeometry(id), 1000);
    }
    const vp = g.viewpoint;
    const dist = g.relay.map((p) => Math.hypot(p[0] - vp[0], p[1] - vp[1], p[2] - vp[2]));
    const [lo, hi] = extent(dist);
    view.setPoints('relay', g.relay, { colour: (i) => css(cmap(VIRIDIS, (dist[i] - lo) / (hi - lo || 1))), size: 1.6 });
    view.setPoints('illumination', g.illumination, { colour: '#e74c3c', size: 2.2, alpha: 0.8 });
    view.setPoints('detection', g.detection, { colour: '#1abc9c', size: 1.6, alpha: 0.8 });
    view.setLines('volume', boxEdges(g.volume.x, g.volume.y, g.volume.z), { colour: '#888', alpha: 0.8 });
    // Axes from the volume's lower corner, 10 cm each: x red, y green, z blue.
    const o = [g.volume.x[0], g.volume.y[0], g.volume.z[0]];
    view.setLines('axis-x', [[o, [o[0] + 0.1, o[1], o[2]]]], { colour: '#e74c3c', width: 3 });
    view.setLines('axis-y', [[o, [o[0], o[1] + 0.1, o[2]]]], { colour: '#27ae60', width: 3 });
    view.setLines('axis-z', [[o, [o[0], o[1], o[2] + 0.1]]], { colour: '#2e86c1', width: 3 });
    view.frame([...g.relay, ...boxEdges(g.volume.x, g.volume.y, g.volume.z).flat()]);
    $('cb-lo').textContent = `${lo.toFixed(2)} m`;
    $('cb-hi').textContent = `${hi.toFixed(2)} m from the instrument`;
    $('view-colourbar').hidden = g.relay.length === 0;
    const relay = g.relay.length
      ? `${g.relay.length.toLocaleString()} relay points coloured by distance (${lo.toFixed(2)}–${hi.toFixed(2)} m)`
      : 'no relay points';
    $('view-caption').textContent = `${relay} · ${g.illumination.length} illumination (red), ${g.detection.length} detection (green) points · volume box`;
    probe.geometry = { relay: g.relay.length, illumination: g.illumination.length, detection: g.detection.length };
  } catch (e) {
    // Another run chosen: nothing to say. Cancelled for the E-STOP: loaded again at
    // the next status.
    if (signal.aborted || id !== selected) return;
    if (e.name === 'AbortError') geometryStage = null;
    else $('view-caption').textContent = e.message;
  }
}

function onHistogram(h) {
  const n = h.bins.length;
  const w = (h.bin_width_ps * h.group) / 1000;
  const t0 = h.offset_ps / 1000;
  const xs = new Array(n);
  for (let i = 0; i < n; i++) xs[i] = t0 + (i + 0.5) * w;
  histPlot.setData([xs, h.bins]);
  const total = h.bins.reduce((a, b) => a + b, 0);
  liveReading = { run: selected, at: performance.now(), laser: h.laser_deg, spad: h.spad_deg, rate: total / Math.max(h.dwell_us * 1e-6, 1e-9), pair: h.pair };
  const measured = status?.pairs_total ? ` · ${status.pairs_done.toLocaleString()} of ${status.pairs_total.toLocaleString()} measured (the capture visits the plan in interleaved passes)` : '';
  $('hist-caption').textContent = `plan pair #${h.pair} · ${total.toLocaleString()} counts · ${h.group > 1 ? `${h.group} bins summed per point` : 'every bin'}${measured}`;
  // The current pair: yellow (illumination) and violet (detection), apart from the red
  // and green planned points.
  view.setPoints('pair', [h.illumination, h.detection], { colour: (i) => (i === 0 ? '#ffd400' : '#8e44ad'), size: 7 });
  view.setLines('pair-link', [[h.illumination, h.detection]], { colour: '#333', width: 2 });
  probe.histograms += 1;
  requestAnimationFrame(() => setTimeout(() => {
    probe.latencies.push(Date.now() - h.unix_ms);
    if (probe.latencies.length > 10000) probe.latencies.shift();
  }, 0));
}

// An adaptive capture chose a batch: its pairs' detection points join the 3-D view,
// coloured by the expected gain each had when chosen (inferno, relative to the largest
// so far); pairs taken for coverage (farthest from everything measured) are grey.
function onPairsChosen(b) {
  chosenBatches.set(b.batch, b);
  drawChosen();
}

function drawChosen() {
  const batches = [...chosenBatches.values()].sort((a, b) => a.batch - b.batch);
  if (!batches.length) return;
  const points = [];
  const gains = [];
  for (const b of batches) {
    b.detection.forEach((p, i) => {
      points.push(p);
      gains.push(b.gains[i]);
    });
  }
  const gmax = Math.max(extent(gains)[1], 1e-30);
  view.setPoints('chosen', points, {
    colour: (i) => (gains[i] > 0 ? css(cmap(INFERNO, 0.25 + 0.75 * gains[i] / gmax)) : '#9aa0a6'),
    size: 4,
    alpha: 0.95,
  });
  const last = batches[batches.length - 1];
  const byGain = gains.filter((g) => g > 0).length;
  const rel = last.relative_gain == null ? '' : `, the last at ${last.relative_gain.toFixed(2)} of the first chosen batch's gain`;
  $('chosen-caption').textContent = ` · adaptive capture: ${points.length.toLocaleString()} pairs chosen in ${batches.length} batches (${byGain} by expected gain, inferno up to ${gmax.toFixed(2)} nats; ${points.length - byGain} for coverage, grey${rel})`;
  probe.chosen = points.length;
  probe.chosenBatches = batches.length;
}

function onSnapshot(s) {
  const wmax = Math.max(extent(s.weights)[1], 1e-30);
  view.setPoints('gaussians', s.centres, {
    colour: '#f39c12',
    size: (i) => 1 + 3 * Math.sqrt(Math.max(0, s.weights[i]) / wmax),
    alpha: 0.75,
  });
  $('gauss-caption').textContent = `${s.centres.length.toLocaleString()} Gaussians (orange, size by weight)`;
  probe.snapshots += 1;
}

// A `lagged` event's catch-up: under way, and when the last one ended.
let catchingUp = false;
let caughtUpAt = -Infinity;

function onEvent(name, data) {
  probe.lastEvent = name;
  switch (name) {
    case 'status':
      onStatus(data);
      break;
    case 'stage-started':
      // A stage started: whatever suspender held the run has let it go (a run paused
      // by one and resumed by the operator says no `suspend-cleared`).
      if (suspension) {
        suspension = null;
        suspensionLiveAt = performance.now();
      }
      if (status) {
        status.stage = data.stage;
        renderSummary();
      }
      // The pairs are stored by the time the capture starts: show them.
      if (data.stage === 'capture') loadGeometry(selected);
      break;
    case 'pair':
      // A pair measured: no suspender holds the run now (its `suspend-cleared` may
      // have been among events skipped for a slow page).
      if (suspension) {
        suspension = null;
        suspensionLiveAt = performance.now();
      }
      if (status) {
        status.pairs_done = data.done;
        status.pairs_total = data.total;
        status.progress = data.done / data.total;
        renderSummary();
      }
      break;
    case 'suspended':
      // A suspender tripped (the interlock opened, a count rate over the plan's
      // limit, ...): the laser is off and the run waits, or pauses, until it clears.
      suspension = { reason: data.reason, resume: data.resume };
      suspensionLiveAt = performance.now();
      renderSummary();
      break;
    case 'suspend-cleared':
      suspension = null;
      suspensionLiveAt = performance.now();
      renderSummary();
      break;
    case 'planned':
    case 'relay':
      geometryStage = null;
      refreshRuns();
      break;
    case 'histogram':
      onHistogram(data);
      break;
    case 'epoch':
      lossSteps.set(data.step, data.loss);
      if (status) status.loss = data.loss;
      drawLoss();
      break;
    case 'snapshot':
      onSnapshot(data);
      break;
    case 'pairs-chosen':
      onPairsChosen(data);
      break;
    case 'failed':
      banner(`run ${selected} failed: ${data.message}`, 'error', selected);
      break;
    case 'lagged':
      // The page fell behind and the daemon skipped events: what was missed is in
      // the run's status and its event log, read again at most every 5 s and one
      // catch-up at a time (a page lags when it is busy; reloads must not add to it).
      probe.lagged = (probe.lagged || 0) + 1;
      if (selected && !catchingUp && performance.now() - caughtUpAt > 5000) {
        const id = selected;
        catchingUp = true;
        Promise.allSettled([api('GET', `/api/v1/runs/${id}`).then(onStatus), loadHistory(id)]).finally(() => {
          catchingUp = false;
          caughtUpAt = performance.now();
        });
      }
      break;
    default:
      break;
  }
}

// The event stream, read with fetch so the token travels in a header. A dropped
// stream reconnects and catches up from the run's status and events.jsonl.
async function follow(id) {
  // One stream per run, and none while the tab is hidden (shown again, it follows).
  if (document.hidden || (live && live.id === id && !live.abort.signal.aborted)) return;
  if (live) live.abort.abort();
  const abort = new AbortController();
  live = { id, abort };
  let delay = 500;
  // Whether the stream brought anything past its status snapshot: only then does the
  // event log hold more than the page already loaded.
  let received = false;
  while (!abort.signal.aborted && selected === id) {
    // This connection's own end: however the stream ends (the daemon closes it, a
    // handler throws, the watchdog gives up on it), it is closed before another opens,
    // so none is left holding one of the browser's six connections to the daemon.
    const conn = new AbortController();
    // A handler's own failure and its event, told apart from the network's failures
    // (both may be TypeErrors).
    let broke = null;
    const watchdog = silenceWatchdog(RUN_STREAM_SILENT_MS, 1000, () => {
      probe.runStreamSilences = (probe.runStreamSilences || 0) + 1;
      conn.abort();
    });
    try {
      const r = await fetch(`/api/v1/runs/${id}/events`, { headers: headers(), signal: AbortSignal.any([abort.signal, conn.signal]) });
      answeredAt = performance.now();
      if (!r.ok) throw new ApiError(r.status, null, `event stream: ${r.status}`);
      probe.streamsOpened += 1;
      setConnection(true);
      await readEvents(r, (name, data) => {
        // A loop another has replaced shows nothing more.
        if (live?.abort !== abort) return;
        if (name !== 'status') received = true;
        try {
          onEvent(name, data);
        } catch (e) {
          broke = { e, name };
          throw e;
        }
      }, watchdog.heard);
    } catch (e) {
      if (abort.signal.aborted) return;
      if (e === broke?.e) console.error(`run ${id}: showing a \`${broke.name}\` event failed; the stream is opened again`, e);
      else if (e instanceof TypeError) setConnection(false);
    } finally {
      watchdog.stop();
      conn.abort();
    }
    // The stream ended: the run stopped, or the connection dropped. Catch up.
    let st = null;
    try {
      st = await api('GET', `/api/v1/runs/${id}`);
      onStatus(st);
    } catch {
      // Unreachable: retry below.
    }
    if (st && !['running', 'queued'].includes(st.state)) {
      if (received) await loadHistory(id);
      await refreshRuns();
      if (live?.abort === abort) live = null;
      return;
    }
    if (st && received) await loadHistory(id);
    // A stream that brought events was live: the next drop starts the backoff again.
    // One that closed on its status alone (a run its run.json calls running that the
    // daemon does not hold) backs off as a refused one does, not every 0.5 s.
    if (received) delay = 500;
    received = false;
    await new Promise((ok) => setTimeout(ok, delay));
    delay = Math.min(delay * 2, 8000);
  }
}

// ---------------------------------------------------------------- results

// The largest volume.npy the page loads: 256 MiB of voxels (a 512×512×256 float32
// volume) and room for its header. A larger one would hold the tab's memory for what a
// screen cannot show; its depth.png and albedo.png are offered as downloads instead.
const VOLUME_LIMIT_BYTES = 256 * 2 ** 20 + 64 * 2 ** 10;

// The plane a view across `axis` is drawn in, as [columns, rows]: the other two axes in
// x, y, z order, as volume.json's `depth` names them for the depth map (recon's
// `DepthAxis::lateral`), so the albedo and the projection along the depth axis lie as
// the depth map does.
const LATERAL = { x: ['y', 'z'], y: ['x', 'z'], z: ['x', 'y'] };

// volume.json's depth map: the axis it looks along, which way leads away from the
// relay, and its columns and rows (older runs' volume.json had none: z for our walls).
const depthOf = (vj) => vj.depth || { axis: 'z', away: '+', columns: 'x', rows: 'y' };

// The array work (.npy parsing; the volume, its projections and slices) runs in a
// worker (volume-worker.js), off the thread that also runs the E-STOP button. It
// answers in order; choosing another run while it works stops it (`stopWorker`).
let worker = null;
const jobs = new Map(); // request id → { resolve, reject }
let jobsAsked = 0;
function stopWorker(why) {
  worker?.terminate();
  worker = null;
  for (const job of jobs.values()) job.reject(why);
  jobs.clear();
}
function inWorker(request, transfer = []) {
  if (!worker) {
    worker = new Worker('/ui/volume-worker.js');
    worker.onmessage = ({ data }) => {
      const job = jobs.get(data.id);
      jobs.delete(data.id);
      if (data.error) job?.reject(new Error(data.error));
      else job?.resolve(data);
    };
    // A worker that did not load (or broke): every request waiting on it fails.
    worker.onerror = (e) => {
      e.preventDefault();
      stopWorker(new Error(`the page's volume worker (/ui/volume-worker.js) ${e.message ? `failed: ${e.message}` : 'did not start'}`));
    };
  }
  const id = ++jobsAsked;
  return new Promise((resolve, reject) => {
    jobs.set(id, { resolve, reject });
    worker.postMessage({ ...request, id }, transfer);
  });
}

const niceStep = (span, n) => {
  const raw = span / n;
  const p = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 5, 10].map((m) => m * p).find((s) => s >= raw);
};
const ticks = (lo, hi, n) => {
  const s = niceStep(hi - lo, n);
  const out = [];
  for (let v = Math.ceil(lo / s) * s; v <= hi + 1e-9; v += s) out.push(+v.toFixed(6));
  return out;
};

// Draws a 2-D map (row-major [rows][cols], row 0 at the bottom) with metric axes and a
// colour bar. NaN pixels are left grey.
function drawMap(canvas, { data, cols, rows, xr, yr, xlabel, ylabel, vmin, vmax, stops, unit, title }) {
  const f = (v) => (v !== 0 && (Math.abs(v) < 0.01 || Math.abs(v) >= 1e4) ? v.toExponential(1) : v.toFixed(2));
  canvas.setAttribute('aria-label', `${title}: ${cols} by ${rows} pixels, ${xlabel} from ${f(xr[0])} to ${f(xr[1])} across, ${ylabel} from ${f(yr[0])} to ${f(yr[1])} upwards, ${unit} coloured from ${f(vmin)} to ${f(vmax)}`);
  const scale = Math.max(1, Math.floor(320 / Math.max(cols, rows)));
  const [pw, ph] = [cols * scale, rows * scale];
  const [ml, mt, mb, mr] = [56, 22, 42, 100];
  canvas.width = ml + pw + mr;
  canvas.height = mt + ph + mb;
  const ctx = canvas.getContext('2d');
  ctx.fillStyle = '#fff';
  ctx.fillRect(0, 0, canvas.width, canvas.height);
  const img = ctx.createImageData(cols, rows);
  // The colour map in 256 steps, as many as a channel holds.
  const lut = Array.from({ length: 256 }, (_, i) => cmap(stops, i / 255));
  const span = vmax - vmin || 1;
  for (let r = 0; r < rows; r++) {
    for (let c = 0; c < cols; c++) {
      const v = data[r * cols + c];
      const o = ((rows - 1 - r) * cols + c) * 4;
      const t = (v - vmin) / span;
      const rgb = Number.isFinite(v) ? lut[t > 0 ? (t < 1 ? Math.round(255 * t) : 255) : 0] : [200, 200, 200];
      img.data[o] = rgb[0];
      img.data[o + 1] = rgb[1];
      img.data[o + 2] = rgb[2];
      img.data[o + 3] = 255;
    }
  }
  const tmp = document.createElement('canvas');
  tmp.width = cols;
  tmp.height = rows;
  tmp.getContext('2d').putImageData(img, 0, 0);
  ctx.imageSmoothingEnabled = false;
  ctx.drawImage(tmp, ml, mt, pw, ph);
  ctx.strokeStyle = '#333';
  ctx.strokeRect(ml, mt, pw, ph);
  ctx.fillStyle = '#222';
  ctx.font = '11px sans-serif';
  ctx.textAlign = 'center';
  for (const t of ticks(xr[0], xr[1], 5)) {
    const x = ml + ((t - xr[0]) / (xr[1] - xr[0])) * pw;
    ctx.fillRect(x, mt + ph, 1, 4);
    ctx.fillText(t.toFixed(2), x, mt + ph + 15);
  }
  ctx.fillText(xlabel, ml + pw / 2, mt + ph + 32);
  ctx.textAlign = 'right';
  for (const t of ticks(yr[0], yr[1], 5)) {
    const y = mt + ph - ((t - yr[0]) / (yr[1] - yr[0])) * ph;
    ctx.fillRect(ml - 4, y, 4, 1);
    ctx.fillText(t.toFixed(2), ml - 6, y + 4);
  }
  ctx.save();
  ctx.translate(14, mt + ph / 2);
  ctx.rotate(-Math.PI / 2);
  ctx.textAlign = 'center';
  ctx.fillText(ylabel, 0, 0);
  ctx.restore();
  ctx.textAlign = 'left';
  ctx.fillText(title, ml, 14);
  // Colour bar.
  const bx = ml + pw + 14;
  for (let y = 0; y < ph; y++) {
    ctx.fillStyle = css(cmap(stops, 1 - y / ph));
    ctx.fillRect(bx, mt + y, 14, 1);
  }
  ctx.strokeRect(bx, mt, 14, ph);
  ctx.fillStyle = '#222';
  // vmin above vmax reverses the bar (a depth map whose relay faces −y: near is dark).
  for (const t of ticks(Math.min(vmin, vmax), Math.max(vmin, vmax), 4)) {
    const y = mt + ph - ((t - vmin) / (vmax - vmin || 1)) * ph;
    ctx.fillRect(bx + 14, y, 4, 1);
    ctx.fillText(Math.abs(vmax) < 0.01 || Math.abs(vmax) >= 1e4 ? t.toExponential(1) : t.toFixed(2), bx + 20, y + 4);
  }
  ctx.save();
  ctx.translate(bx + 84, mt + ph / 2);
  ctx.rotate(-Math.PI / 2);
  ctx.textAlign = 'center';
  ctx.fillText(unit, 0, 0);
  ctx.restore();
}

// The shown volume (the worker holds its voxels): { id, nx, ny, nz, json, max }.
let volume = null;

// Metric axes for a plane of the volume across `along` (volume.json's ranges).
function axesOf(along, json) {
  const [columns, rows] = LATERAL[along];
  return { xlabel: `${columns} (m)`, ylabel: `${rows} (m)`, xr: json[columns], yr: json[rows] };
}

// The slice the slider and the axis menu choose, from the worker: one at a time, and
// a choice made while one is under way drawn when it is in.
let sliceBusy = false;
let sliceAgain = false;
async function drawSlice() {
  if (!volume) return;
  if (sliceBusy) {
    sliceAgain = true;
    return;
  }
  sliceBusy = true;
  sliceAgain = false;
  const v = volume;
  try {
    const axis = $('slice-axis').value;
    const n = { x: v.nx, y: v.ny, z: v.nz }[axis];
    const slider = $('slice');
    slider.max = n - 1;
    const i = Math.min(Number(slider.value), n - 1);
    const [columns, rows] = LATERAL[axis];
    const p = await inWorker({ op: 'slice', along: axis, columns, rows, index: i });
    if (volume !== v) return;
    const range = v.json[axis];
    const pos = range[0] + ((i + 0.5) * (range[1] - range[0])) / n;
    drawMap($('slice-canvas'), { ...p, ...axesOf(axis, v.json), vmin: 0, vmax: v.max, stops: INFERNO, unit: 'intensity', title: `slice ${axis} = ${pos.toFixed(3)} m (${i + 1}/${n})` });
    probe.sliceShown = true;
  } catch (e) {
    if (volume === v && e.name !== 'Superseded') $('volume-note').textContent = `the slice could not be shown: ${e.message}`;
  } finally {
    sliceBusy = false;
    if (sliceAgain) drawSlice();
  }
}
$('slice').addEventListener('input', drawSlice);
$('slice-axis').addEventListener('change', () => {
  const n = { x: volume?.nx, y: volume?.ny, z: volume?.nz }[$('slice-axis').value] || 1;
  $('slice').max = n - 1;
  $('slice').value = Math.floor(n / 2);
  drawSlice();
});

// Results load lazily: the depth map and the volume's description at once (small),
// the volume itself (megabytes) only when its part of the page is on screen.
let resultsObserver = null;
function whenVisible(target, f) {
  resultsObserver?.disconnect();
  resultsObserver = new IntersectionObserver((entries) => {
    if (entries.some((e) => e.isIntersecting)) {
      resultsObserver.disconnect();
      f();
    }
  });
  resultsObserver.observe(target);
}

async function loadResults(id) {
  const signal = selection.signal;
  // A retry of an earlier volume load that failed is this load's to make now: two
  // would hold two of the daemon's download slots.
  clearTimeout(volumeRetry);
  volumeRetry = null;
  try {
    const [vj, depthBuf] = await Promise.all([
      api('GET', `/api/v1/runs/${id}/files/volume.json`, undefined, null, signal),
      fetchBytes(`/api/v1/runs/${id}/files/depth.npy`, Infinity, signal),
    ]);
    if (id !== selected) return;
    const depth = await inWorker({ op: 'parse', buffer: depthBuf }, [depthBuf]);
    if (id !== selected) return;
    if (depth.shape.length !== 2) throw new Error(`depth.npy has shape (${depth.shape.join(', ')}), not rows and columns`);
    // The depth map looks along the volume's axis nearest the relay's normal (z for our
    // walls; volume.json says which, and which way leads away from the relay).
    const d = depthOf(vj);
    const [near, far] = d.away === '-' ? [vj[d.axis][1], vj[d.axis][0]] : vj[d.axis];
    drawMap($('depth-canvas'), {
      data: depth.data, cols: depth.shape[1], rows: depth.shape[0], xr: vj[d.columns], yr: vj[d.rows],
      xlabel: `${d.columns} (m)`, ylabel: `${d.rows} (m)`, vmin: near, vmax: far, stops: VIRIDIS, unit: `depth ${d.axis} (m)`, title: 'depth (grey: no surface)',
    });
    const [nz, ny, nx] = vj.shape_zyx;
    $('results-note').textContent = `${vj.method} with ${vj.solver}, ${vj.pairs.toLocaleString()} pairs, ${nx}×${ny}×${nz} voxels of ${vj.voxel_m.map((v) => (v * 1000).toFixed(1)).join(' × ')} mm${vj.final_loss != null ? `, final loss ${vj.final_loss.toExponential(3)}` : ''}`;
    $('volume-note').textContent = 'the volume loads when this part of the page is shown';
    $('results-body').hidden = false;
    probe.resultsShown = true;
    resultsFailures = 0;
    whenVisible($('volume-part'), () => loadVolume(id, vj, signal));
  } catch (e) {
    // Superseded, or cancelled with its selection: another run was chosen (or this
    // one again), and nothing is to be said of this load.
    if (e.name === 'Superseded' || signal.aborted || id !== selected) return;
    if (e.name === 'AbortError') {
      // Cancelled for the E-STOP: loaded again at the next status.
      if (resultsFor === id) resultsFor = null;
    } else if (mayPass(e)) {
      // The daemon busy (503 `too-many-downloads`), failing or out of reach: loaded
      // again at a status once the wait is over (`onStatus`).
      const wait = retryDelay(resultsFailures++);
      if (resultsFor === id) resultsFor = null;
      resultsRetryAt = performance.now() + wait;
      $('results-note').textContent = `results could not be loaded: ${e.message} (trying again in ${wait / 1000} s)`;
    } else {
      $('results-note').textContent = `results could not be shown: ${e.message}`;
    }
  }
}

// The volume: fetched (at most VOLUME_LIMIT_BYTES), handed to the worker, which
// keeps it and sends back its maximum and projections; slices are asked for as shown.
async function loadVolume(id, vj, signal) {
  // Another run chosen since this one's results were drawn: not its volume.
  if (signal.aborted) return;
  const note = $('volume-note');
  try {
    note.textContent = 'loading the volume…';
    const buffer = await fetchBytes(`/api/v1/runs/${id}/files/volume.npy`, VOLUME_LIMIT_BYTES, signal);
    if (id !== selected) return;
    note.textContent = 'projecting the volume…';
    // The projections along z, y and x, and the albedo: the peak along the depth map's
    // axis, in the depth map's columns and rows (the same view as one of the three).
    const d = depthOf(vj);
    const views = ['z', 'y', 'x'].map((along) => ({ along, columns: LATERAL[along][0], rows: LATERAL[along][1] }));
    let a = views.findIndex((v) => v.along === d.axis && v.columns === d.columns && v.rows === d.rows);
    if (a < 0) a = views.push({ along: d.axis, columns: d.columns, rows: d.rows }) - 1;
    const got = await inWorker({ op: 'load', buffer, views }, [buffer]);
    if (id !== selected) return;
    const [nz, ny, nx] = got.shape;
    volume = { id, nx, ny, nz, json: vj, max: got.max || 1 };
    const albedo = got.planes[a];
    // One map a task (a 512×512 one takes some 40 ms to colour): a click on the E-STOP
    // between them is handled at once.
    const yieldToPage = () => new Promise((ok) => setTimeout(ok, 0));
    drawMap($('albedo-canvas'), {
      ...albedo, xlabel: `${d.columns} (m)`, ylabel: `${d.rows} (m)`, xr: vj[d.columns], yr: vj[d.rows],
      data: albedo.data.map((v) => Math.max(0, v) / volume.max), vmin: 0, vmax: 1, stops: INFERNO, unit: 'relative intensity', title: `albedo (peak along ${d.axis})`,
    });
    for (const [i, { along }] of views.slice(0, 3).entries()) {
      await yieldToPage();
      if (id !== selected) return;
      drawMap($(`mip-${along}`), { ...got.planes[i], ...axesOf(along, vj), vmin: 0, vmax: volume.max, stops: INFERNO, unit: 'intensity', title: `max projection along ${along}` });
    }
    $('slice-axis').value = 'z';
    $('slice').max = nz - 1;
    $('slice').value = Math.floor(nz / 2);
    drawSlice();
    const odd = got.nonFinite ? `; ${got.nonFinite.toLocaleString()} voxels are NaN or infinite (left out of the maximum)` : '';
    note.textContent = `${nx}×${ny}×${nz} voxels, maximum ${volume.max.toExponential(2)}${odd}`;
    volumeFailures = 0;
  } catch (e) {
    // Superseded or cancelled with its selection: another run's volume, nothing to say.
    if (e.name === 'Superseded' || signal.aborted || id !== selected) return;
    if (e.name === 'AbortError') {
      // Cancelled for the E-STOP: loaded again at the next status.
      if (resultsFor === id) resultsFor = null;
    } else if (e.name === 'TooLarge') {
      note.textContent = `${e.message}: the albedo, the projections and the slices are not drawn here. Download depth.png and albedo.png below (or volume.npy, to open it with numpy).`;
    } else if (mayPass(e)) {
      // The daemon busy (503 `too-many-downloads`), failing or out of reach: the
      // volume alone is asked for again after a wait, when its part is shown.
      const wait = retryDelay(volumeFailures++);
      note.textContent = `the volume could not be loaded: ${e.message} (trying again in ${wait / 1000} s)`;
      clearTimeout(volumeRetry);
      volumeRetry = setTimeout(() => {
        volumeRetry = null;
        if (!signal.aborted) whenVisible($('volume-part'), () => loadVolume(id, vj, signal));
      }, wait);
    } else {
      note.textContent = `the volume could not be shown: ${e.message}`;
    }
  }
}

// ---------------------------------------------------------------- start

// One refresh at a time: a slow daemon must not pile requests up in the browser's few
// connections (the E-STOP needs one).
let refreshing = false;
async function refresh() {
  // A hidden tab polls nothing: its connections are shared with the tab in use.
  if (refreshing || document.hidden) return;
  refreshing = true;
  try {
    // One after another: one connection for the polls, beside the two streams. The
    // E-STOP's check first, so its label is the freshest thing on the page (a daemon
    // that stops answering holds each poll for up to 6 s).
    for (const poll of [checkEstop, pollInstrument, refreshRuns, checkQueue]) await poll();
  } finally {
    refreshing = false;
  }
}

async function checkQueue() {
  const sentAt = performance.now();
  try {
    queueLock = (await api('GET', '/api/v1/queue', undefined, POLL_TIMEOUT_MS)).lock;
  } catch (e) {
    if (e.name === 'AbortError') return;
    if (e.name === 'TimeoutError') pollTimedOut(sentAt);
    // Not known: Submit waits until it is.
    queueLock = { by: 'unknown', reason: 'the queue could not be read' };
  }
  updateSubmit();
}

// A hidden tab gives back its connections (a browser has six per host, shared by its
// tabs, and the E-STOP of the tab in use needs one): its run stream closes, and opens
// again when the tab is shown.
document.addEventListener('visibilitychange', () => {
  if (document.hidden) {
    if (live) live.abort.abort();
    live = null;
  } else if (selected && status && ['running', 'queued'].includes(status.state)) {
    follow(selected);
  }
});

async function start() {
  showTokenState();
  makePlots();
  drawLines();
  startSafety({ headers, probe, setConnection, answered: () => { answeredAt = performance.now(); } });
  $('runs-filter').addEventListener('input', () => refreshRuns());
  $('runs-state').addEventListener('change', () => refreshRuns());
  await refresh();
  refreshAudit();
  setInterval(refreshAudit, 10 * POLL_MS);
  probe.loadMs = performance.now();
  probe.ready = true;
  setInterval(refresh, POLL_MS);
  setInterval(() => {
    renderInstrument();
    renderSummary();
  }, 1000);
}

start();
