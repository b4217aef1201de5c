// A 3-D point viewer on a 2-D canvas: orbit by dragging, zoom with the wheel, layers of
// coloured points and line segments drawn back to front. It needs no WebGL (headless
// browsers and remote desktops often lack it) and draws a few 10^4 points per frame.

export class View3D {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext('2d');
    this.layers = new Map();
    this.yaw = -0.7;
    this.pitch = 0.35;
    this.zoom = 1;
    this.centre = [0, 0, 0];
    this.radius = 1;
    this.pending = false;
    this.frames = 0;
    let last = null;
    canvas.addEventListener('pointerdown', (e) => {
      last = [e.clientX, e.clientY];
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!last) return;
      this.yaw += (e.clientX - last[0]) * 0.01;
      this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + (e.clientY - last[1]) * 0.01));
      last = [e.clientX, e.clientY];
      this.redraw();
    });
    canvas.addEventListener('pointerup', () => { last = null; });
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      this.zoom = Math.max(0.2, Math.min(20, this.zoom * Math.exp(-e.deltaY * 0.001)));
      this.redraw();
    }, { passive: false });
  }

  // A layer of points: `points` is [[x, y, z], ...]; `colour` is a CSS colour or a
  // function of the point's index; `size` a radius in pixels or a function of the index.
  setPoints(name, points, style) {
    this.layers.set(name, { kind: 'points', points, ...style });
    this.redraw();
  }

  // A layer of segments: `segments` is [[[x, y, z], [x, y, z]], ...].
  setLines(name, segments, style) {
    this.layers.set(name, { kind: 'lines', segments, ...style });
    this.redraw();
  }

  clear() {
    this.layers.clear();
    this.redraw();
  }

  // Centres the view on `points` (a bounding sphere).
  frame(points) {
    if (!points.length) return;
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    for (const p of points) {
      for (let i = 0; i < 3; i++) {
        lo[i] = Math.min(lo[i], p[i]);
        hi[i] = Math.max(hi[i], p[i]);
      }
    }
    this.centre = lo.map((v, i) => 0.5 * (v + hi[i]));
    this.radius = Math.max(1e-3, 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]));
    this.redraw();
  }

  redraw() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.draw();
    });
  }

  // World to screen: orbit about the centre, then a perspective divide. The camera
  // frame is right-handed (x right, y up, z towards the viewer) and the camera looks
  // along its −z: at yaw 0 and pitch 0 the world is seen along −z with x to the right
  // and y up, as the instrument sees a relay wall at z = 0 from z = 2 m, and as the
  // depth map draws it. (A camera whose depth grows along +z is a left-handed frame: it
  // draws the world mirrored.) Returns [x, y, depth] with depth growing away from the
  // viewer.
  project(p) {
    const [w, h] = [this.canvas.width, this.canvas.height];
    const x = p[0] - this.centre[0];
    const y = p[1] - this.centre[1];
    const z = p[2] - this.centre[2];
    // Yaw about y, then pitch about x: both proper rotations.
    const cy = Math.cos(this.yaw), sy = Math.sin(this.yaw);
    const cp = Math.cos(this.pitch), sp = Math.sin(this.pitch);
    const x1 = cy * x + sy * z;
    const z1 = -sy * x + cy * z;
    const y2 = cp * y - sp * z1;
    const z2 = sp * y + cp * z1;
    // The eye sits at z = dist in the rotated frame: a point's distance from it along
    // the view is dist − z2.
    const dist = 3 * this.radius;
    const away = dist - z2;
    const f = (0.45 * Math.min(w, h) * this.zoom * dist) / this.radius / Math.max(away, 1e-3 * dist);
    return [w / 2 + x1 * f, h / 2 - y2 * f, -z2];
  }

  draw() {
    const ctx = this.ctx;
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    const items = [];
    for (const layer of this.layers.values()) {
      if (layer.kind === 'lines') {
        ctx.strokeStyle = layer.colour;
        ctx.globalAlpha = layer.alpha ?? 1;
        ctx.lineWidth = layer.width ?? 1;
        ctx.beginPath();
        for (const [a, b] of layer.segments) {
          const pa = this.project(a);
          const pb = this.project(b);
          ctx.moveTo(pa[0], pa[1]);
          ctx.lineTo(pb[0], pb[1]);
        }
        ctx.stroke();
        continue;
      }
      const colour = layer.colour;
      const size = layer.size ?? 2;
      layer.points.forEach((p, i) => {
        const [sx, sy, d] = this.project(p);
        items.push([d, sx, sy, typeof colour === 'function' ? colour(i) : colour,
          typeof size === 'function' ? size(i) : size, layer.alpha ?? 1]);
      });
    }
    items.sort((a, b) => b[0] - a[0]);
    for (const [, x, y, c, s, a] of items) {
      ctx.globalAlpha = a;
      ctx.fillStyle = c;
      ctx.fillRect(x - s, y - s, 2 * s, 2 * s);
    }
    ctx.globalAlpha = 1;
    this.frames += 1;
  }
}

// The 12 edges of an axis-aligned box.
export function boxEdges(x, y, z) {
  const c = (i) => [x[i & 1], y[(i >> 1) & 1], z[(i >> 2) & 1]];
  const edges = [];
  for (let i = 0; i < 8; i++) {
    for (const bit of [1, 2, 4]) {
      if (!(i & bit)) edges.push([c(i), c(i | bit)]);
    }
  }
  return edges;
}
