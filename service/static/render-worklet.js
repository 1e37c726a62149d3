// hapticlink texture renderer for the operator console: an AudioWorklet that synthesises a served rendering model
// (GET /library/{id}/model, schema "hapticlink.render-model" v1) from the operator's speed and force.
//
// Rendering semantics are those of the operator's Python renderer (texture_library/renderer.py StreamRenderer),
// sample for sample at the model's rate (1 kHz): clamp speed to [0, max_speed] and force to [0, max_force]; find the enclosing triangle of the
// (speed, force) grid with both axes normalised by their max (a point outside every triangle takes the one it is
// least outside of, weights clipped ≥ 0 and renormalised); interpolate ar_lsf, ma_lsf, variance and gain
// barycentrically; LSF → polynomial (texture_library/lsf.py); then, poles first (renderer.py arma_poles_first:
// the same filter as synthesis.py render's direct form, without its bursts when the coefficients move fast)
//     w[n] = e[n] − Σ_{i≥1} ar[i]·w[n−i],   y[n] = Σ_j gain·ma[j]·w[n−j],   e[n] = N(0, 1)·√variance.
//
// From the model's rate to the AudioContext's rate (44.1 kHz, 48 kHz, …): band-limited interpolation with a
// Kaiser-windowed sinc of RESAMPLE_HALF_WIDTH source samples on each side, cut off at the source's Nyquist
// frequency. The output lags the 1 kHz stream by RESAMPLE_HALF_WIDTH source samples (16 ms). Output sample k sits
// at source time t = k·rate_hz/sampleRate − 16, computed in exact integer arithmetic (no drift), and takes
// Σ_m x[m]·h(t − m) over the 32 source samples around t. Because the sinc is 1 at 0 and 0 at every other integer,
// an output sample that falls exactly on a source instant (every 48th at 48 kHz) IS that 1 kHz sample: the 1 kHz
// stream is recovered exactly by taking those samples. The kernel is tabulated at 1/512 of a source sample and
// interpolated linearly (error < 1e-5 of full scale).
//
// The four dimensions, as texture_library/renderer.py renders them (StreamRenderer; the same arithmetic):
// - vibration: the ARMA model above, its variance held at or above the corner floor v_r·min(1, s/s_r)²·min(1, f/f_r)
//   ((s_r, f_r, v_r): the grid point with the smallest non-zero variance, texture_library/synthesis.py corner_floor),
//   so a grid corner whose three points are silent does not silence a slow stroke;
// - bumps: the model's surface profile z(x) = h·(1 + cos 2πx/P)/2 felt as z''(x)·v² + z'(x)·v̇ (m/s², ×1e-3) at the
//   operator's position x (mm), with v and v̇ by backward differences (at the first position the tool is at rest);
// - taps: at a touchdown (the contact speed, mm/s), the recorded tap nearest that speed (the first of equals)
//   scaled by contact speed / its recorded speed, played out whole;
// - friction is the device's (μ·F); a sound card cannot render it.
// A `trajectory` (speed, force, position and touchdown per 1 kHz sample) is rendered exactly so, sample for sample
// (no smoothing, no gate): the parity tests feed the same trajectory to both renderers.
//
// On top of the renderer, as the console's input conditioning (none of it changes the synthesis):
// - a model switch is crossfaded (equal power, `crossfade_ms`, 50 ms by default) between two renderers that run
//   side by side; the incoming one is pre-rolled for PREROLL_SAMPLES at the current speed and force so its filter
//   state is settled when it becomes audible;
// - speed and force are smoothed with a one-pole filter (`smoothing_ms`, 15 ms by default; 0 = none);
// - a contact gate: silent while the pad is not touched, ramping in and out over 5 ms; at speeds under
//   GATE_SPEED_MM_S the vibration and bumps fade in proportion to speed (a finger held still makes no vibration);
//   taps are not gated (a touchdown is at speed 0);
// - the position along the bumps (the pad's x axis, mm) is smoothed by two such one-pole stages in a row, so the
//   velocity the bumps read is continuous between the page's control messages; a touch starts at its own
//   position (no sweep from the last one), at rest;
// - a touch (contact going from off to on) taps at the control message's `touchdown_mm_s`;
// - acceleration (m/s²) is scaled to the audio signal by `full_scale` (the acceleration that maps to ±1; 40 m/s² by
//   default, as `hapticlink operator --full-scale`; the console page sets its own) and
//   clipped to ±1; the level messages say what share of their samples clipped.
//
// The file also runs outside an AudioWorklet (a page or a test can import the classes): the processor is
// registered only where registerProcessor exists.

"use strict";

const SCHEMA = "hapticlink.render-model";
const FULL_SCALE = 40; // m/s² at ±1 (drivers/operator/outputs.py FULL_SCALE)
const SCHEMA_VERSION = 1;
const RESAMPLE_HALF_WIDTH = 16; // source samples on each side of the interpolation kernel (= output delay)
const KAISER_BETA = 7.0; // ≈ 70 dB stop band
const KERNEL_STEPS = 512; // table points per source sample
const PREROLL_SAMPLES = 256; // source samples an incoming model runs before its crossfade starts
const GATE_SPEED_MM_S = 5.0;
const GATE_RAMP_MS = 5.0;
const MAX_GRID_POINTS = 4096;
const MAX_ORDER = 128;
const MAX_TAPS = 64;
const MAX_TAP_SAMPLES = 4096;

// ---- the model ---------------------------------------------------------------------------------------------------
function fail(message) {
  throw new Error("render model: " + message);
}

function finiteArray(value, name, length) {
  if (!Array.isArray(value)) fail(`${name} must be an array`);
  if (length !== undefined && value.length !== length) fail(`${name} must have ${length} entries, got ${value.length}`);
  const out = new Float64Array(value.length);
  for (let i = 0; i < value.length; i++) {
    const v = value[i];
    if (typeof v !== "number" || !Number.isFinite(v)) fail(`${name}[${i}] is not a finite number`);
    out[i] = v;
  }
  return out;
}

function lsfRows(value, name, m) {
  if (!Array.isArray(value) || value.length !== m) fail(`${name} must have ${m} rows`);
  const order = Array.isArray(value[0]) ? value[0].length : -1;
  if (order < 0 || order > MAX_ORDER) fail(`${name} rows must be arrays of at most ${MAX_ORDER} frequencies`);
  const out = new Float64Array(m * order);
  for (let r = 0; r < m; r++) {
    const row = finiteArray(value[r], `${name}[${r}]`, order);
    for (let i = 0; i < order; i++) {
      if (!(row[i] > 0 && row[i] < Math.PI) || (i > 0 && !(row[i] > row[i - 1]))) {
        fail(`${name}[${r}] must increase strictly inside (0, π)`);
      }
      out[r * order + i] = row[i];
    }
  }
  return { data: out, order };
}

/** A served rendering model (JSON object), checked and turned into typed arrays; throws Error naming the problem. */
function parseModel(json) {
  if (json === null || typeof json !== "object") fail("not a JSON object");
  if (json.schema !== SCHEMA) fail(`schema must be "${SCHEMA}", got ${JSON.stringify(json.schema)}`);
  if (json.schema_version !== SCHEMA_VERSION) fail(`schema_version ${json.schema_version} is not ${SCHEMA_VERSION}`);
  const speeds = finiteArray(json.speeds_mm_s, "speeds_mm_s");
  const m = speeds.length;
  if (m < 3 || m > MAX_GRID_POINTS) fail(`the grid must have 3 to ${MAX_GRID_POINTS} points, got ${m}`);
  const forces = finiteArray(json.forces_n, "forces_n", m);
  const variance = finiteArray(json.variance, "variance", m);
  const gain = finiteArray(json.gain, "gain", m);
  for (let i = 0; i < m; i++) if (variance[i] < 0) fail(`variance[${i}] is negative`);
  if (!Array.isArray(json.triangles) || json.triangles.length < 1) fail("triangles must be a non-empty array");
  const triangles = new Int32Array(json.triangles.length * 3);
  json.triangles.forEach((t, k) => {
    if (!Array.isArray(t) || t.length !== 3) fail(`triangles[${k}] must have 3 vertex indices`);
    for (let j = 0; j < 3; j++) {
      if (!Number.isInteger(t[j]) || t[j] < 0 || t[j] >= m) fail(`triangles[${k}] indices must lie in [0, ${m - 1}]`);
      triangles[3 * k + j] = t[j];
    }
  });
  const ar = lsfRows(json.ar_lsf, "ar_lsf", m);
  const ma = lsfRows(json.ma_lsf, "ma_lsf", m);
  const maxSpeed = json.max_speed_mm_s, maxForce = json.max_force_n, rate = json.rate_hz;
  if (!(maxSpeed > 0 && Number.isFinite(maxSpeed))) fail("max_speed_mm_s must be > 0");
  if (!(maxForce > 0 && Number.isFinite(maxForce))) fail("max_force_n must be > 0");
  if (!(Number.isInteger(rate) && rate >= 100 && rate <= 20000)) fail(`rate_hz must be a whole number of Hz in [100, 20000], got ${rate}`);
  let surface = null;
  if (json.surface !== null && json.surface !== undefined) {
    const h = json.surface.bump_height_mm, period = json.surface.bump_period_mm;
    if (!(Number.isFinite(h) && h >= 0)) fail("surface.bump_height_mm must be a finite number ≥ 0");
    if (!(Number.isFinite(period) && period > 0)) fail("surface.bump_period_mm must be a finite number > 0");
    surface = {height: h, period};
  }
  let taps = null;
  if (json.taps !== null && json.taps !== undefined) {
    const tapSpeeds = finiteArray(json.taps.speeds_mm_s, "taps.speeds_mm_s");
    const k = tapSpeeds.length;
    if (k < 1 || k > MAX_TAPS) fail(`taps must hold 1 to ${MAX_TAPS} transients, got ${k}`);
    if (!Array.isArray(json.taps.accel) || json.taps.accel.length !== k) fail(`taps.accel must have ${k} rows`);
    const width = Array.isArray(json.taps.accel[0]) ? json.taps.accel[0].length : -1;
    if (width < 1 || width > MAX_TAP_SAMPLES) fail(`taps.accel rows must hold 1 to ${MAX_TAP_SAMPLES} samples`);
    taps = {speeds: tapSpeeds, accel: json.taps.accel.map((row, i) => finiteArray(row, `taps.accel[${i}]`, width))};
  }
  // the quietest vibrating grid point: the corner floor's reference (synthesis.py quietest_point)
  let quiet = null;
  for (let i = 0; i < m; i++) if (variance[i] > 0 && (quiet === null || variance[i] < variance[quiet])) quiet = i;
  return {
    id: String(json.id), modelVersion: String(json.model_version), name: String(json.name),
    rateHz: rate, speeds, forces, triangles, arLsf: ar.data, p: ar.order, maLsf: ma.data, q: ma.order,
    variance, gain, maxSpeed, maxForce, mu: Number(json.mu), surface, taps,
    floorRef: quiet === null ? null : {speed: speeds[quiet], force: forces[quiet], variance: variance[quiet]},
  };
}

/** The least variance played at (speed, force): texture_library/synthesis.py corner_floor. */
function cornerFloor(model, speed, force) {
  const ref = model.floorRef;
  if (ref === null) return 0;
  const s = Math.min(Math.max(speed, 0), model.maxSpeed), f = Math.min(Math.max(force, 0), model.maxForce);
  const rs = ref.speed > 0 ? Math.min(1, s / ref.speed) : 1, rf = ref.force > 0 ? Math.min(1, f / ref.force) : 1;
  return ref.variance * (rs * rs) * rf;
}

/** Bump acceleration z''(x)·v² + z'(x)·v̇, m/s², of a surface {height, period} (texture_library/surface.py accel_at). */
function bumpAccel(surface, x, v, dv) {
  const k = (2 * Math.PI) / surface.period, half = 0.5 * surface.height;
  const dz = -half * k * Math.sin(k * x), d2z = -half * k * k * Math.cos(k * x);
  return (d2z * v * v + dz * dv) * 1e-3;
}

/** The tap played at a touchdown at contactSpeed mm/s (texture_library/renderer.py tap_transient), or null. */
function tapTransient(model, contactSpeed) {
  const taps = model.taps;
  if (taps === null || !(contactSpeed > 0) || model.rateHz !== 1000) return null;
  let best = 0;
  for (let i = 1; i < taps.speeds.length; i++) {
    if (Math.abs(taps.speeds[i] - contactSpeed) < Math.abs(taps.speeds[best] - contactSpeed)) best = i;
  }
  const scale = taps.speeds[best] > 0 ? contactSpeed / taps.speeds[best] : 1;
  const row = taps.accel[best], out = new Float64Array(row.length);
  for (let i = 0; i < row.length; i++) out[i] = scale * row[i];
  return out;
}

// ---- the maths of texture_library/synthesis.py and lsf.py -------------------------------------------------------
/** Enclosing triangle and barycentric weights of one (speed, force) point: {idx: [3], w: [3]}. */
function barycentric(model, speed, force) {
  const s = Math.min(Math.max(speed, 0), model.maxSpeed) / model.maxSpeed;
  const f = Math.min(Math.max(force, 0), model.maxForce) / model.maxForce;
  const gs = model.speeds, gf = model.forces, tri = model.triangles;
  let best = -1, bestWorst = -Infinity, b0 = 0, b1 = 0, b2 = 0;
  for (let k = 0; k < tri.length / 3; k++) {
    const i0 = tri[3 * k], i1 = tri[3 * k + 1], i2 = tri[3 * k + 2];
    const x0 = gs[i0] / model.maxSpeed, y0 = gf[i0] / model.maxForce;
    const x1 = gs[i1] / model.maxSpeed, y1 = gf[i1] / model.maxForce;
    const x2 = gs[i2] / model.maxSpeed, y2 = gf[i2] / model.maxForce;
    const det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2);
    if (Math.abs(det) < 1e-15) continue; // degenerate triangles never win
    const l0 = ((y1 - y2) * (s - x2) + (x2 - x1) * (f - y2)) / det;
    const l1 = ((y2 - y0) * (s - x2) + (x0 - x2) * (f - y2)) / det;
    const l2 = 1.0 - l0 - l1;
    const worst = Math.min(Math.min(l0, l1), l2);
    if (best < 0 || worst > bestWorst) { best = k; bestWorst = worst; b0 = l0; b1 = l1; b2 = l2; }
  }
  if (best < 0) best = 0;
  b0 = Math.max(b0, 0); b1 = Math.max(b1, 0); b2 = Math.max(b2, 0);
  const sum = b0 + b1 + b2;
  return { idx: [tri[3 * best], tri[3 * best + 1], tri[3 * best + 2]], w: [b0 / sum, b1 / sum, b2 / sum] };
}

// poly ← poly · ∏ (1 − 2cos ωᵢ z⁻¹ + z⁻²) over lsf[first], lsf[first + 2], … in place (poly starts as [1]);
// the sums run in texture_library/lsf.py's order, so both give the same doubles
function expandInto(lsf, first, poly) {
  poly.fill(0);
  poly[0] = 1.0;
  let length = 1;
  for (let i = first; i < lsf.length; i += 2) {
    const c = -2.0 * Math.cos(lsf[i]);
    for (let j = length + 1; j >= 0; j--) {
      let v = poly[j];
      if (j >= 1 && j - 1 < length) v += c * poly[j - 1];
      if (j >= 2) v += poly[j - 2];
      poly[j] = v;
    }
    length += 2;
  }
  return length;
}

/** Scratch arrays for lsfToPolyInto of order p. */
function polyScratch(p) {
  return { pPoly: new Float64Array(p + 3), qPoly: new Float64Array(p + 3), pFull: new Float64Array(p + 2), qFull: new Float64Array(p + 2) };
}

/** Monic polynomial a (p+1) from p line spectral frequencies (radians, strictly increasing in (0, π)), no allocation. */
function lsfToPolyInto(lsf, a, scratch) {
  const p = lsf.length;
  a[0] = 1.0;
  if (p === 0) return a;
  const { pPoly, qPoly, pFull, qFull } = scratch;
  const np = expandInto(lsf, 0, pPoly), nq = expandInto(lsf, 1, qPoly);
  pFull.fill(0); qFull.fill(0);
  if (p % 2 === 0) { // P gets the root at z = −1, Q the root at z = +1
    for (let i = 0; i < np; i++) pFull[i] += pPoly[i];
    for (let i = 0; i < np; i++) pFull[i + 1] += pPoly[i];
    for (let i = 0; i < nq; i++) qFull[i] += qPoly[i];
    for (let i = 0; i < nq; i++) qFull[i + 1] -= qPoly[i];
  } else { // odd order: Q holds the roots ±1
    for (let i = 0; i < np; i++) pFull[i] = pPoly[i];
    for (let i = 0; i < nq; i++) qFull[i] += qPoly[i];
    for (let i = 0; i < nq; i++) qFull[i + 2] -= qPoly[i];
  }
  for (let i = 0; i <= p; i++) a[i] = 0.5 * (pFull[i] + qFull[i]);
  return a;
}

/** Monic polynomial (p+1) from p line spectral frequencies (radians, strictly increasing in (0, π)). */
function lsfToPoly(lsf) {
  return lsfToPolyInto(lsf, new Float64Array(lsf.length + 1), polyScratch(lsf.length));
}

/** One stateful ARMA renderer of one model: step(speed mm/s, force N, unit normal) → acceleration m/s². */
class ArmaVoice {
  constructor(model) {
    this.model = model;
    this.w = new Float64Array(Math.max(model.p, model.q, 1) + 1); // w[n … n−L], newest first
    this.n = 0;
    this.lastSpeed = NaN; this.lastForce = NaN;
    this.ar = new Float64Array(model.p + 1); this.bma = new Float64Array(model.q + 1); this.sd = 0;
    this.arLsf = new Float64Array(model.p); this.maLsf = new Float64Array(model.q);
    this.arScratch = polyScratch(model.p); this.maScratch = polyScratch(model.q);
  }

  parameters(speed, force) {
    const m = this.model, { idx, w } = barycentric(m, speed, force);
    const mix = (arr, order, out) => {
      for (let i = 0; i < order; i++) {
        out[i] = w[0] * arr[idx[0] * order + i] + w[1] * arr[idx[1] * order + i] + w[2] * arr[idx[2] * order + i];
      }
      return out;
    };
    lsfToPolyInto(mix(m.arLsf, m.p, this.arLsf), this.ar, this.arScratch);
    const ma = lsfToPolyInto(mix(m.maLsf, m.q, this.maLsf), this.bma, this.maScratch);
    const g = w[0] * m.gain[idx[0]] + w[1] * m.gain[idx[1]] + w[2] * m.gain[idx[2]];
    for (let j = 0; j < ma.length; j++) ma[j] *= g;
    const v = w[0] * m.variance[idx[0]] + w[1] * m.variance[idx[1]] + w[2] * m.variance[idx[2]];
    this.sd = Math.sqrt(Math.max(v, 0, cornerFloor(m, speed, force)));
    this.lastSpeed = speed; this.lastForce = force;
  }

  step(speed, force, unitNormal) {
    if (speed !== this.lastSpeed || force !== this.lastForce) this.parameters(speed, force);
    const w = this.w, p = this.model.p, q = this.model.q;
    for (let j = w.length - 1; j > 0; j--) w[j] = w[j - 1]; // w[1 …] now hold w[n−1 …]
    let acc = unitNormal * this.sd;
    for (let i = 1; i <= p; i++) acc -= this.ar[i] * w[i];
    w[0] = acc;
    let out = 0.0;
    for (let j = 0; j <= q; j++) out += this.bma[j] * w[j];
    this.n++;
    return out;
  }
}

/** Seeded standard normals: xoshiro128** seeded by splitmix32, Box–Muller in pairs. */
class Gaussian {
  constructor(seed) {
    let x = seed >>> 0;
    const splitmix = () => {
      x = (x + 0x9e3779b9) >>> 0;
      let z = x;
      z = Math.imul(z ^ (z >>> 16), 0x85ebca6b) >>> 0;
      z = Math.imul(z ^ (z >>> 13), 0xc2b2ae35) >>> 0;
      return (z ^ (z >>> 16)) >>> 0;
    };
    this.s = new Uint32Array([splitmix(), splitmix(), splitmix(), splitmix()]);
    this.spare = null;
  }

  uniform() { // (0, 1)
    const s = this.s;
    const result = Math.imul(((Math.imul(s[1], 5) << 7) | (Math.imul(s[1], 5) >>> 25)) >>> 0, 9) >>> 0;
    const t = (s[1] << 9) >>> 0;
    s[2] ^= s[0]; s[3] ^= s[1]; s[1] ^= s[2]; s[0] ^= s[3]; s[2] ^= t;
    s[3] = ((s[3] << 11) | (s[3] >>> 21)) >>> 0;
    return (result + 0.5) / 4294967296;
  }

  next() {
    if (this.spare !== null) { const v = this.spare; this.spare = null; return v; }
    const r = Math.sqrt(-2.0 * Math.log(this.uniform())), phi = 2.0 * Math.PI * this.uniform();
    this.spare = r * Math.sin(phi);
    return r * Math.cos(phi);
  }
}

// ---- resampling --------------------------------------------------------------------------------------------------
function besselI0(x) {
  let sum = 1.0, term = 1.0;
  for (let k = 1; k < 64; k++) {
    term *= (x / (2 * k)) * (x / (2 * k));
    sum += term;
    if (term < 1e-17 * sum) break;
  }
  return sum;
}

/** h(d) = sinc(d)·kaiser(d / K) on [−K, K], tabulated every 1/KERNEL_STEPS (exactly 1 at 0, 0 at other integers). */
function kernelTable(halfWidth = RESAMPLE_HALF_WIDTH, beta = KAISER_BETA) {
  const n = 2 * halfWidth * KERNEL_STEPS + 1, table = new Float64Array(n + 1);
  const norm = besselI0(beta);
  for (let i = 0; i < n; i++) {
    const d = i / KERNEL_STEPS - halfWidth;
    if (i % KERNEL_STEPS === 0) { table[i] = d === 0 ? 1.0 : 0.0; continue; }
    const u = d / halfWidth;
    const window = besselI0(beta * Math.sqrt(Math.max(0, 1 - u * u))) / norm;
    table[i] = (Math.sin(Math.PI * d) / (Math.PI * d)) * window;
  }
  return table;
}

/** Band-limited interpolation of a stream at sourceRate (whole Hz) to outputRate: pull(produce) → next output sample. */
class Resampler {
  constructor(sourceRate, outputRate, halfWidth = RESAMPLE_HALF_WIDTH) {
    this.sourceRate = sourceRate; this.outputRate = outputRate; this.K = halfWidth;
    this.table = kernelTable(halfWidth);
    this.ring = new Float64Array(2 * halfWidth); // the last 2K source samples
    this.produced = 0; // source samples pulled so far
    this.index = 0; // floor(k·sourceRate / outputRate) of the next output sample k
    this.remainder = 0; // (k·sourceRate) mod outputRate, exact
  }

  next(produce) {
    const K = this.K, ring = this.ring, size = 2 * K;
    while (this.produced <= this.index) { ring[this.produced % size] = produce(); this.produced++; }
    // output time t = index − K + frac; taps m = index − 2K + 1 … index, d = t − m
    const frac = this.remainder / this.outputRate;
    let acc = 0.0;
    for (let j = 0; j < size; j++) {
      const m = this.index - j;
      if (m < 0) break;
      const pos = (frac - K + j) * KERNEL_STEPS + K * KERNEL_STEPS; // (d + K)·steps, d = frac − K + j
      const i0 = Math.floor(pos), a = pos - i0;
      const h = a === 0 ? this.table[i0] : this.table[i0] + a * (this.table[i0 + 1] - this.table[i0]);
      acc += ring[m % size] * h;
    }
    this.remainder += this.sourceRate;
    while (this.remainder >= this.outputRate) { this.remainder -= this.outputRate; this.index++; }
    return acc;
  }
}

// ---- the console's renderer: switches, input conditioning, gate ---------------------------------------------------
/** A trajectory option checked: {n, speed, force, position|null, touchdown|null} as Float64Arrays. */
function checkTrajectory(tr) {
  const speed = finiteArray(tr.speed_mm_s, "trajectory.speed_mm_s"), n = speed.length;
  if (n < 1) throw new Error("trajectory: speed_mm_s is empty");
  const force = finiteArray(tr.force_n, "trajectory.force_n", n);
  const position = tr.position_mm ? finiteArray(tr.position_mm, "trajectory.position_mm", n) : null;
  const touchdown = tr.touchdown_mm_s ? finiteArray(tr.touchdown_mm_s, "trajectory.touchdown_mm_s", n) : null;
  return {n, speed, force, position, touchdown};
}

class TextureRenderer {
  /** options: {seed, excitation (unit normals to use first, for reproducing a Python render), speed_mm_s, force_n,
   *  position_mm, contact, touchdown_mm_s, smoothing_ms, crossfade_ms, full_scale (m/s² at ±1), trajectory:
   *  {speed_mm_s, force_n, position_mm?, touchdown_mm_s?} (arrays, one entry per 1 kHz sample, rendered as given
   *  with neither smoothing nor gate; after its end the last speed and force hold, still without a gate)}. */
  constructor(outputRate, options = {}) {
    this.outputRate = outputRate;
    this.rateHz = 1000; // until a model says otherwise
    this.noise = new Gaussian(options.seed === undefined ? 1 : options.seed);
    this.excitation = options.excitation ? Float64Array.from(options.excitation) : null;
    this.drawn = 0;
    this.speed = options.speed_mm_s || 0; this.force = options.force_n || 0;
    this.targetSpeed = this.speed; this.targetForce = this.force;
    this.contact = !!options.contact;
    this.gate = this.gateTarget();
    this.trajectory = options.trajectory ? checkTrajectory(options.trajectory) : null;
    // position along the bumps (mm): the target, two smoothing stages; null until a position is known
    this.targetPosition = Number.isFinite(options.position_mm) ? options.position_mm : null;
    this.p1 = this.targetPosition; this.position = this.targetPosition;
    this.lastX = null; this.lastV = 0; // backward differences: the sample before (at rest at the first position)
    this.touchdown = Number.isFinite(options.touchdown_mm_s) ? options.touchdown_mm_s : 0;
    this.tapNow = this.contact && this.touchdown > 0; // a renderer made in contact starts with its touchdown
    this.taps = []; // sounding taps: {data, at}
    this.smoothingMs = options.smoothing_ms === undefined ? 15 : options.smoothing_ms;
    this.crossfadeMs = options.crossfade_ms === undefined ? 50 : options.crossfade_ms;
    this.fullScale = options.full_scale || FULL_SCALE;
    this.voice = null; this.incoming = null; this.fade = 0; this.fadeLength = 0;
    this.pending = []; // {model, atSample, crossfadeMs}
    this.sample = 0; // source samples rendered
    this.events = []; // messages for the main thread
    this.resampler = new Resampler(this.rateHz, outputRate);
    this.sumSquares = 0; this.count = 0; this.clipped = 0;
  }

  gateTarget() {
    if (!this.contact) return 0;
    return Math.min(1, this.speed / GATE_SPEED_MM_S);
  }

  unitNormal() {
    const v = this.excitation && this.drawn < this.excitation.length ? this.excitation[this.drawn] : this.noise.next();
    this.drawn++;
    return v;
  }

  /** Schedule a switch to `model` (parsed) at source sample atSample (now when undefined). */
  load(model, atSample, crossfadeMs) {
    this.pending.push({ model, atSample: atSample === undefined ? this.sample : atSample, crossfadeMs });
  }

  control(speed, force, contact, position, touchdown) {
    if (Number.isFinite(speed)) this.targetSpeed = Math.max(0, speed);
    if (Number.isFinite(force)) this.targetForce = Math.max(0, force);
    if (Number.isFinite(touchdown)) this.touchdown = Math.max(0, touchdown);
    const touching = contact === undefined ? this.contact : !!contact;
    if (touching && !this.contact) {
      this.tapNow = this.touchdown > 0;
      this.p1 = null; this.position = null; // a touch starts where it lands, at rest
    }
    this.contact = touching;
    if (Number.isFinite(position)) this.targetPosition = position;
  }

  /** The next position (mm) and its backward-difference velocity (mm/s) and acceleration (mm/s²), or null. */
  motion(x) {
    if (x === null) { this.lastX = null; this.lastV = 0; return null; }
    const x0 = this.lastX === null ? x : this.lastX, v0 = this.lastX === null ? 0 : this.lastV;
    const v = (x - x0) * this.rateHz, dv = (v - v0) * this.rateHz;
    this.lastX = x; this.lastV = v;
    return {x, v, dv};
  }

  /** One voice's sample: its vibration plus its model's bumps at `m` (null: no position). */
  voiceSample(voice, unitNormal, m) {
    let y = voice.step(this.speed, this.force, unitNormal);
    if (m !== null && voice.model.surface !== null) y += bumpAccel(voice.model.surface, m.x, m.v, m.dv);
    return y;
  }

  startSwitch(item) {
    if (this.voice === null || item.crossfadeMs === 0 || (item.crossfadeMs === undefined && this.crossfadeMs === 0)) {
      if (this.voice === null && item.model.rateHz !== this.rateHz) {
        this.rateHz = item.model.rateHz;
        this.resampler = new Resampler(this.rateHz, this.outputRate);
      }
      this.voice = new ArmaVoice(item.model); this.incoming = null;
      this.events.push({ type: "switched", id: item.model.id, model_version: item.model.modelVersion, sample: this.sample, crossfade_ms: 0 });
      return;
    }
    if (item.model.rateHz !== this.rateHz) {
      this.events.push({ type: "error", message: `render model ${item.model.id}: rate_hz ${item.model.rateHz} differs from the playing model's ${this.rateHz}` });
      return;
    }
    const incoming = new ArmaVoice(item.model);
    // pre-roll: the incoming filter settles at the current operating point before it is heard (its own noise)
    const preroll = new Gaussian((this.sample * 2654435761) >>> 0);
    for (let i = 0; i < PREROLL_SAMPLES; i++) incoming.step(this.speed, this.force, preroll.next());
    if (this.incoming !== null) this.voice = this.incoming; // a switch during a switch: the newer one wins
    this.incoming = incoming;
    this.fadeLength = Math.max(1, Math.round(((item.crossfadeMs === undefined ? this.crossfadeMs : item.crossfadeMs) * this.rateHz) / 1000));
    this.fade = 0;
    this.events.push({ type: "switched", id: item.model.id, model_version: item.model.modelVersion, sample: this.sample, crossfade_ms: (this.fadeLength * 1000) / this.rateHz });
  }

  /** One source-rate sample (m/s², after crossfade and gate; before full-scale). */
  sourceSample() {
    while (this.pending.length && this.pending[0].atSample <= this.sample) this.startSwitch(this.pending.shift());
    const tr = this.trajectory;
    let x = null, touchdown = 0;
    if (tr !== null) {
      const k = Math.min(this.sample, tr.n - 1), inside = this.sample < tr.n;
      this.speed = tr.speed[k]; this.force = tr.force[k]; this.gate = 1;
      x = tr.position === null || !inside ? null : tr.position[k];
      touchdown = tr.touchdown === null || !inside ? 0 : tr.touchdown[k];
    } else {
      const alpha = this.smoothingMs > 0 ? 1 - Math.exp(-1000 / (this.rateHz * this.smoothingMs)) : 1;
      this.speed += alpha * (this.targetSpeed - this.speed);
      this.force += alpha * (this.targetForce - this.force);
      const ramp = 1000 / (this.rateHz * GATE_RAMP_MS), target = this.gateTarget();
      this.gate += Math.max(-ramp, Math.min(ramp, target - this.gate));
      if (this.contact && this.targetPosition !== null) {
        if (this.position === null) { this.p1 = this.targetPosition; this.position = this.targetPosition; }
        this.p1 += alpha * (this.targetPosition - this.p1);
        this.position += alpha * (this.p1 - this.position);
        x = this.position;
      }
      if (this.tapNow) { touchdown = this.touchdown; this.tapNow = false; }
    }
    const m = this.motion(x);
    this.sample++;
    if (this.voice === null) return 0;
    let y = this.voiceSample(this.voice, this.unitNormal(), m);
    if (this.incoming !== null) {
      const u = (this.fade + 0.5) / this.fadeLength;
      const z = this.voiceSample(this.incoming, this.noise.next(), m);
      y = Math.cos(0.5 * Math.PI * u) * y + Math.sin(0.5 * Math.PI * u) * z;
      if (++this.fade >= this.fadeLength) { this.voice = this.incoming; this.incoming = null; }
    }
    y *= this.gate;
    if (touchdown > 0) {
      const tap = tapTransient((this.incoming || this.voice).model, touchdown);
      if (tap !== null) this.taps.push({data: tap, at: 0});
    }
    for (let i = this.taps.length - 1; i >= 0; i--) {
      const t = this.taps[i];
      y += t.data[t.at++];
      if (t.at >= t.data.length) this.taps.splice(i, 1);
    }
    return y;
  }

  /** Fill `out` (Float32Array at the output rate) with the signal scaled by full_scale and clipped to ±1. */
  render(out) {
    const scale = 1 / this.fullScale;
    const produce = () => this.sourceSample();
    for (let i = 0; i < out.length; i++) {
      const v = this.resampler.next(produce) * scale;
      this.sumSquares += v * v; this.count++;
      if (v > 1 || v < -1) this.clipped++;
      out[i] = v > 1 ? 1 : v < -1 ? -1 : v;
    }
  }
}

if (typeof registerProcessor === "function") {
  class HapticlinkRenderProcessor extends AudioWorkletProcessor {
    // processorOptions: TextureRenderer's options, and models: [{model, at_s?, crossfade_ms?}] to schedule at once.
    // Messages in: {type: "model", model: <render-model JSON>, at_s?, crossfade_ms?}, {type: "control", speed_mm_s,
    // force_n, contact, position_mm?, touchdown_mm_s?}, {type: "full_scale", value}. Out: {type: "switched" | "error" | "level", …}.
    constructor(options) {
      super();
      const opts = (options && options.processorOptions) || {};
      this.renderer = new TextureRenderer(sampleRate, opts);
      this.levelEvery = Math.round(sampleRate / 10);
      this.port.onmessage = (event) => this.onMessage(event.data);
      for (const item of opts.models || []) this.onMessage({ type: "model", ...item }); // scheduled before any rendering
      this.port.postMessage({ type: "ready", sample_rate: sampleRate, latency_ms: (RESAMPLE_HALF_WIDTH * 1000) / this.renderer.rateHz });
    }

    onMessage(msg) {
      const r = this.renderer;
      if (msg.type === "model") {
        try {
          const model = parseModel(msg.model);
          const at = msg.at_s === undefined ? undefined : Math.round(msg.at_s * model.rateHz);
          r.load(model, at, msg.crossfade_ms);
        } catch (err) {
          this.port.postMessage({ type: "error", message: String(err.message || err) }); // the last good model plays on
        }
      } else if (msg.type === "control") {
        r.control(msg.speed_mm_s, msg.force_n, msg.contact, msg.position_mm, msg.touchdown_mm_s);
      } else if (msg.type === "full_scale" && msg.value > 0) {
        r.fullScale = msg.value;
      }
    }

    process(inputs, outputs) {
      const out = outputs[0];
      const r = this.renderer;
      r.render(out[0]);
      for (let c = 1; c < out.length; c++) out[c].set(out[0]);
      while (r.events.length) this.port.postMessage(r.events.shift());
      if (r.count >= this.levelEvery) {
        this.port.postMessage({
          type: "level", rms: Math.sqrt(r.sumSquares / r.count), clipped: r.clipped / r.count,
          speed_mm_s: r.speed, force_n: r.force,
        });
        r.sumSquares = 0; r.count = 0; r.clipped = 0;
      }
      return true;
    }
  }
  registerProcessor("hapticlink-render", HapticlinkRenderProcessor);
}
