// Server-sent events read with fetch (so the key travels in a header, which
// EventSource cannot send). Shared by the run stream (app.js) and the safety stream
// (safety.js).

// The event-stream parser of the HTML standard's "Interpreting an event stream", less
// what this page does not use (`id`, `retry`): lines end in CRLF, LF or CR; a line
// starting with a colon is a comment (the server's keep-alive); a field's value loses
// one leading space; the values of an event's `data` lines are joined with LF; a blank
// line dispatches the event, named `message` unless an `event` line said otherwise.
// Returns push(text), to be fed the decoded stream in pieces cut anywhere. Every event
// this page reads carries JSON: one without data is not dispatched (nothing to parse).
export function eventParser(onEvent) {
  const EOL = /\r\n|\r|\n/g;
  let buf = '';
  let name = '';
  let data = [];
  // The last piece ended in a CR: an LF that opens the next one ends no line of its own.
  let afterCr = false;
  return (text) => {
    buf += text;
    let at = 0;
    if (afterCr && buf.startsWith('\n')) at = 1;
    afterCr = false;
    for (;;) {
      EOL.lastIndex = at;
      const m = EOL.exec(buf);
      if (!m) break;
      const line = buf.slice(at, m.index);
      at = EOL.lastIndex;
      afterCr = m[0] === '\r' && at === buf.length;
      if (line === '') {
        const event = name || 'message';
        const payload = data.join('\n');
        name = '';
        data = [];
        if (payload) onEvent(event, JSON.parse(payload));
        continue;
      }
      if (line.startsWith(':')) continue;
      const colon = line.indexOf(':');
      const field = colon < 0 ? line : line.slice(0, colon);
      const value = colon < 0 ? '' : line.slice(colon + 1).replace(/^ /, '');
      if (field === 'event') name = value;
      else if (field === 'data') data.push(value);
    }
    buf = buf.slice(at);
  };
}

// Calls onSilent() at each check (every checkMs) once nothing has been heard for
// limitMs: heard() says something arrived, stop() ends the watch. The event streams'
// guard against a connection that went quiet without closing.
export function silenceWatchdog(limitMs, checkMs, onSilent) {
  let last = performance.now();
  const timer = setInterval(() => {
    if (performance.now() - last > limitMs) onSilent();
  }, checkMs);
  return {
    heard: () => { last = performance.now(); },
    stop: () => clearInterval(timer),
  };
}

// Calls onEvent(name, json) for each event with data until the stream ends, and
// onBytes() whenever anything arrives, keep-alive comments included (for a silence
// watchdog). The response's body is cancelled however this returns, so a handler that
// throws does not leave the connection open.
export async function readEvents(response, onEvent, onBytes = () => {}) {
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  const push = eventParser(onEvent);
  try {
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      onBytes();
      push(value);
    }
  } finally {
    reader.cancel().catch(() => {});
  }
}
