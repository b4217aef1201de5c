// The live safety bar and the time series, fed by GET /api/v1/instrument/events (a
// `safety` event every 0.5 s from the daemon: the running run's own laser readings, or
// the idle reading). The bar turns to UNKNOWN when the stream stops for STREAM_STALE_MS
// or the reading is older than the daemon's stated limit (`stale_after_s`); nothing on
// it is ever shown as known when it is not.

import { readEvents, silenceWatchdog } from '/ui/sse.js';

const STREAM_STALE_MS = 2000;
// A connection with no event for this long is given up and opened again: the daemon
// sends one every 0.5 s, and a connection that went silent (a stalled proxy, a network
// that dropped it without a reset) would otherwise never be noticed.
const STREAM_SILENT_MS = 4000;
// Signal counts per laser pulse past which pile-up distorts the histograms (the usual
// TCSPC rule: keep below 5 %).
const PILE_UP_ALARM = 0.05;
const HOUR_S = 3600;
// A change of the bar's state is said to screen readers once it has held this long,
// so a reading on the edge of its age limit does not chatter; the laser turning on is
// said at once.
const ANNOUNCE_HOLD_MS = 1000;

const $ = (id) => document.getElementById(id);

export function startSafety({ headers, probe, setConnection, answered = () => {} }) {
  let last = null; // { s: safety event, at: performance.now() }
  let streamUp = false;
  // The daemon's refusal of the stream's last request, in words (its status and its
  // message: a 401 key, a 403 role or host, a 503 at the stream cap), shown with the
  // UNKNOWN state: the reason is the operator's to fix, not the network's. Null when the
  // last try was not refused.
  let refused = null;
  const series = { t: [], signal: [], dark: [], pairs: [], pileUp: [], age: [] };
  let plots = null;
  // The daemon's clock less this browser's, seconds: the points carry the daemon's
  // time, and a window drawn on the browser's alone showed nothing (or the wrong
  // minutes) on a machine whose clock was off by more than its range.
  let skew = 0;

  function push(s) {
    const t = s.unix_ms / 1000;
    if (Number.isFinite(t)) skew = t - Date.now() / 1000;
    series.t.push(t);
    series.signal.push(s.signal_rate_hz ?? null);
    series.dark.push(s.emission === false && s.source === 'idle' ? s.detector_rate_hz ?? null : null);
    series.pairs.push(s.pair_rate_hz ?? null);
    series.pileUp.push(s.counts_per_pulse ?? null);
    series.age.push(s.age_s ?? null);
    while (series.t.length && series.t[0] < t - HOUR_S) {
      for (const k of Object.keys(series)) series[k].shift();
    }
  }

  function makePlots() {
    const w = Math.max(260, Math.min(420, ($('series-rates').clientWidth || 400)));
    const mk = (el, yLabel, lines, yLog) => new uPlot({
      width: w, height: 180,
      scales: { x: { time: true }, y: yLog ? { distr: 3 } : {} },
      axes: [{}, { label: yLabel, size: 60 }],
      series: [{}, ...lines],
      legend: { show: true },
    }, [[], ...lines.map(() => [])], el);
    $('series-rates').replaceChildren();
    $('series-pairs').replaceChildren();
    $('series-health').replaceChildren();
    plots = {
      rates: mk($('series-rates'), 'counts/s', [
        { label: 'signal', stroke: '#2a7ab9' },
        { label: 'dark (laser off)', stroke: '#7f8c8d' },
      ], true),
      pairs: mk($('series-pairs'), 'pairs/s · counts/pulse', [
        { label: 'pair rate', stroke: '#27ae60' },
        { label: 'counts per pulse', stroke: '#c0392b' },
      ], false),
      health: mk($('series-health'), 'seconds', [
        { label: 'reading age', stroke: '#8e44ad' },
      ], false),
    };
  }

  function drawSeries() {
    if (!plots) return;
    const range = Number($('series-range').value);
    const now = Date.now() / 1000 + skew;
    const x = { min: now - range, max: now };
    plots.rates.setData([series.t, series.signal, series.dark], false);
    plots.rates.setScale('x', x);
    plots.pairs.setData([series.t, series.pairs, series.pileUp], false);
    plots.pairs.setScale('x', x);
    plots.health.setData([series.t, series.age], false);
    plots.health.setScale('x', x);
  }

  // What is wrong now, in words; empty when all is well.
  function alarms(s, unknown) {
    const out = [];
    if (unknown) out.push(unknown);
    if (!s || unknown) return out;
    if (s.interlock_closed === false) out.push('interlock OPEN');
    if (s.emission && s.source === 'idle') out.push('laser ON with no run measuring');
    if ((s.counts_per_pulse ?? 0) > PILE_UP_ALARM) out.push(`pile-up: ${(100 * s.counts_per_pulse).toFixed(1)} % counts per pulse (keep below ${100 * PILE_UP_ALARM} %)`);
    return out;
  }

  // The bar's state in words (#sb-announce, the bar's one live region): said when it
  // changes, never the ticking age or rates, which would be read out four times a
  // second and bury a change to LASER ON.
  let said = null;
  let change = null; // { key, since }
  function announce(key, text, now, urgent) {
    if (key === said) {
      change = null;
      return;
    }
    if (change?.key !== key) change = { key, since: now };
    if (!urgent && now - change.since < ANNOUNCE_HOLD_MS) return;
    $('sb-announce').textContent = text;
    said = key;
    change = null;
    probe.announced = text;
  }

  function render() {
    const now = performance.now();
    const s = last?.s;
    let unknown = null;
    if (!streamUp || !last || now - last.at > STREAM_STALE_MS) {
      unknown = `no live data from the daemon${!streamUp && refused ? `: it refused the live stream, ${refused}` : ''}`;
    } else if (s.age_s == null || s.emission == null) {
      unknown = 'the laser has not been read yet';
    } else if (!Number.isFinite(s.age_s) || !Number.isFinite(s.stale_after_s)) {
      unknown = 'the daemon sent a reading without its age or its limit';
    } else if (s.age_s + (now - last.at) / 1000 > s.stale_after_s) {
      unknown = `the last reading is ${(s.age_s + (now - last.at) / 1000).toFixed(0)} s old (limit ${s.stale_after_s.toFixed(0)} s)${s.note ? `: ${s.note}` : ''}`;
    }
    const bar = $('safety');
    const word = (id, text, cls) => {
      const e = $(id);
      e.textContent = text;
      e.className = `sb ${cls}`;
    };
    if (unknown) {
      bar.className = 'safety unknown';
      word('sb-state', 'LASER STATE UNKNOWN', 'danger');
      word('sb-emission', `laser ?${s && s.emission != null ? ` (last read ${s.emission ? 'ON' : 'off'})` : ''}`, '');
      word('sb-interlock', 'interlock ?', '');
      word('sb-diffuser', 'diffuser ?', '');
      word('sb-arms', 'arms ?', '');
      word('sb-rate', 'rate ?', '');
      $('sb-age').textContent = `${unknown}. In doubt, use the hardware emergency stop.`;
      announce('unknown', `Laser state unknown: ${unknown}. In doubt, use the hardware emergency stop.`, now, false);
    } else {
      bar.className = `safety ${s.emission ? 'emitting' : 'safe'}`;
      word('sb-state', s.source === 'run' ? `run ${s.run}` : 'idle', '');
      word('sb-emission', s.emission ? 'LASER ON' : 'laser off', s.emission ? 'danger' : 'ok');
      word('sb-interlock', s.interlock_closed == null ? 'interlock ?' : s.interlock_closed ? 'interlock closed' : 'INTERLOCK OPEN', s.interlock_closed === false ? 'danger' : s.interlock_closed ? 'ok' : '');
      word('sb-diffuser', s.diffuser_in == null ? 'diffuser ?' : s.diffuser_in ? 'diffuser in' : 'diffuser out', '');
      const a = (v) => (Array.isArray(v) && v.length === 2 && v.every(Number.isFinite) ? `${v[0].toFixed(2)}°, ${v[1].toFixed(2)}°` : '–');
      word('sb-arms', `laser arm (${a(s.laser_deg)}) · SPAD arm (${a(s.spad_deg)})`, '');
      const rate = s.signal_rate_hz ?? s.detector_rate_hz;
      word('sb-rate', rate == null ? 'rate –' : `${Math.round(rate).toLocaleString()} counts/s${s.signal_rate_hz != null ? ' signal' : ' detector'}`, '');
      $('sb-age').textContent = `read ${(s.age_s + (now - last.at) / 1000).toFixed(1)} s ago (stale after ${s.stale_after_s.toFixed(0)} s)`;
      const open = s.interlock_closed === false;
      const who = s.source === 'run' ? `run ${s.run}` : 'idle';
      announce(`${s.emission ? 'on' : 'off'} ${open ? 'open' : ''} ${who}`,
        `${s.emission ? 'LASER ON' : 'Laser off'}${open ? ', INTERLOCK OPEN' : ''}, ${who}.`, now, Boolean(s.emission));
    }
    const list = alarms(s, unknown);
    const al = $('series-alarm');
    al.textContent = list.length ? `ALARM: ${list.join(' · ')}` : 'no alarm';
    al.className = list.length ? 'alarm' : 'small ok';
    probe.safety = unknown ? 'unknown' : 'known';
    probe.safetyEmission = unknown ? null : s.emission;
    probe.alarms = list;
  }

  // The stream, closed while the tab is hidden (its connection is given back; the bar
  // is not seen then anyway) and opened again when it is shown.
  let abort = null;
  async function stream() {
    let delay = 500;
    for (;;) {
      while (document.hidden) await new Promise((ok) => setTimeout(ok, 500));
      abort = new AbortController();
      const ctl = abort;
      const watchdog = silenceWatchdog(STREAM_SILENT_MS, 500, () => {
        probe.safetySilences = (probe.safetySilences || 0) + 1;
        ctl.abort();
      });
      try {
        const r = await fetch('/api/v1/instrument/events', { headers: headers(), signal: abort.signal });
        answered();
        if (!r.ok) {
          // The API's JSON error, `{error, message}`, where the body is one.
          const body = await r.json().catch(() => null);
          refused = `${r.status}${r.statusText ? ` ${r.statusText}` : ''}${body?.message ? `: ${body.message}` : ''}`;
          probe.safetyRefused = refused;
          throw new Error(`instrument events: ${refused}`);
        }
        refused = null;
        probe.safetyRefused = null;
        // Live only from the first event of this connection on: an event from before a
        // drop is not shown as current again.
        last = null;
        streamUp = true;
        delay = 500;
        await readEvents(r, (name, s) => {
          watchdog.heard();
          if (name !== 'safety') return;
          last = { s, at: performance.now() };
          push(s);
          probe.safetyEvents = (probe.safetyEvents || 0) + 1;
        });
      } catch (e) {
        if (e instanceof TypeError && !document.hidden) {
          // Not reached at all: no refusal to show.
          refused = null;
          setConnection(false);
        }
      } finally {
        watchdog.stop();
      }
      abort?.abort();
      streamUp = false;
      render();
      await new Promise((ok) => setTimeout(ok, delay));
      delay = Math.min(delay * 2, 4000);
    }
  }

  document.addEventListener('visibilitychange', () => {
    if (document.hidden) abort?.abort();
  });
  makePlots();
  $('series-range').addEventListener('change', drawSeries);
  setInterval(render, 250);
  setInterval(drawSeries, 1000);
  render();
  stream();
}
