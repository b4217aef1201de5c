// The dashboard's array work, off the page's thread: it parses .npy files and holds
// the shown run's volume, from which it computes the maximum and the projections and
// slices the page draws. A 512×512×256 volume took 2.6 s of loops on the page's own
// thread, which also runs the E-STOP button; here the page stays live meanwhile.
//
// A classic worker script (no modules), started by app.js from /ui/volume-worker.js:
// same origin, as the page's Content-Security-Policy (script-src 'self') allows.
//
// Requests, each with an `id` the answer repeats (as `{ id, error }` when it fails):
//   { op: 'parse', buffer }: a .npy file's { shape, data } (data a typed array over
//     the same memory: the buffer is moved here and back, not copied).
//   { op: 'load', buffer, views }: keeps the file as the volume (C order, shape
//     [nz, ny, nx]) and answers { shape, max, nonFinite, planes }, a maximum
//     projection for each of `views`.
//   { op: 'slice', along, columns, rows, index }: the kept volume's slice `index`
//     across `along`.
// A view is { along, columns, rows }: the axis collapsed and the plane's column and
// row axes ('x', 'y', 'z'); a plane is { data, cols, rows }, row-major, row 0 first.

'use strict';

// A .npy file's shape and values: little-endian float32 or float64, C order. The
// values are a view on `buffer` where their offset suits the type (numpy pads the
// header to 16 or 64 bytes, so they always do in files it writes), else a copy of
// the values alone.
function parseNpy(buffer) {
  const bytes = new Uint8Array(buffer);
  const magic = String.fromCharCode(...bytes.subarray(1, 6));
  if (bytes.length < 10 || bytes[0] !== 0x93 || magic !== 'NUMPY') throw new Error('not a .npy file');
  const dv = new DataView(buffer);
  const major = bytes[6];
  const start = major >= 2 ? 12 : 10;
  const headerLen = major >= 2 ? dv.getUint32(8, true) : dv.getUint16(8, true);
  if (start + headerLen > bytes.length) throw new Error('the .npy header is cut short');
  const header = new TextDecoder().decode(bytes.subarray(start, start + headerLen));
  const descr = /'descr':\s*'([^']+)'/.exec(header)?.[1];
  const Type = { '<f4': Float32Array, '<f8': Float64Array }[descr];
  if (!Type) throw new Error(`.npy dtype ${descr} is not supported (float32 or float64, little-endian)`);
  if (/'fortran_order':\s*True/.test(header)) throw new Error('Fortran-order .npy is not supported');
  const dims = /'shape':\s*\(([^)]*)\)/.exec(header)?.[1];
  if (dims == null) throw new Error('the .npy header has no shape');
  const shape = dims.split(',').map((s) => s.trim()).filter(Boolean).map(Number);
  if (!shape.every((n) => Number.isSafeInteger(n) && n >= 0)) throw new Error(`.npy shape (${dims}) is not a list of sizes`);
  const count = shape.reduce((a, b) => a * b, 1);
  const offset = start + headerLen;
  const want = count * Type.BYTES_PER_ELEMENT;
  if (bytes.length - offset !== want) {
    throw new Error(`the .npy holds ${bytes.length - offset} bytes of values where its shape (${shape.join(' × ')}) needs ${want}: the file is cut short or damaged`);
  }
  const data = offset % Type.BYTES_PER_ELEMENT === 0
    ? new Type(buffer, offset, count)
    : new Type(buffer.slice(offset));
  return { shape, data };
}

// The largest finite value (at least 0) and how many values are NaN or infinite.
function stats(data) {
  let max = 0;
  let nonFinite = 0;
  for (let i = 0; i < data.length; i++) {
    const v = data[i];
    if (!Number.isFinite(v)) nonFinite++;
    else if (v > max) max = v;
  }
  return { max, nonFinite };
}

// The maximum over `along` from `from` to `to` (exclusive) of a volume { nx, ny, nz,
// data } (x fastest), as a plane with `columns` and `rows`: a projection over the
// whole axis, a slice over one index. The volume is read in memory order. NaN values
// are passed over; a pixel with none other is −Infinity.
function project(volume, { along, columns, rows }, from, to) {
  const n = { x: volume.nx, y: volume.ny, z: volume.nz };
  if ([along, columns, rows].sort().join('') !== 'xyz') throw new Error(`a view of ${along}, ${columns}, ${rows} is not one of the volume's planes`);
  const cols = n[columns];
  const stride = { [along]: 0, [columns]: 1, [rows]: cols };
  const lo = { x: 0, y: 0, z: 0, [along]: from };
  const hi = { ...n, [along]: to };
  const out = new Float32Array(cols * n[rows]).fill(-Infinity);
  const { nx, ny, data } = volume;
  for (let iz = lo.z; iz < hi.z; iz++) {
    for (let iy = lo.y; iy < hi.y; iy++) {
      const base = (iz * ny + iy) * nx;
      let o = iz * stride.z + iy * stride.y + lo.x * stride.x;
      for (let ix = lo.x; ix < hi.x; ix++, o += stride.x) {
        const v = data[base + ix];
        if (v > out[o]) out[o] = v;
      }
    }
  }
  return { data: out, cols, rows: n[rows] };
}

let volume = null;

function handle(m) {
  switch (m.op) {
    case 'parse': {
      const { shape, data } = parseNpy(m.buffer);
      return [{ shape, data }, [data.buffer]];
    }
    case 'load': {
      volume = null;
      const { shape, data } = parseNpy(m.buffer);
      if (shape.length !== 3 || shape.includes(0)) throw new Error(`the volume's shape (${shape.join(' × ')}) is not three sizes above zero`);
      const [nz, ny, nx] = shape;
      volume = { nx, ny, nz, data };
      const { max, nonFinite } = stats(data);
      const planes = m.views.map((view) => project(volume, view, 0, { x: nx, y: ny, z: nz }[view.along]));
      return [{ shape, max, nonFinite, planes }, planes.map((p) => p.data.buffer)];
    }
    case 'slice': {
      if (!volume) throw new Error('no volume is loaded');
      const n = { x: volume.nx, y: volume.ny, z: volume.nz }[m.along];
      if (!(Number.isInteger(m.index) && m.index >= 0 && m.index < n)) throw new Error(`slice ${m.index} is outside 0..${n - 1}`);
      const plane = project(volume, m, m.index, m.index + 1);
      return [plane, [plane.data.buffer]];
    }
    default:
      throw new Error(`unknown request ${m.op}`);
  }
}

self.onmessage = ({ data: m }) => {
  let answer;
  try {
    answer = handle(m);
  } catch (e) {
    self.postMessage({ id: m.id, error: e.message });
    return;
  }
  const [body, transfer] = answer;
  self.postMessage({ ...body, id: m.id }, transfer);
};
