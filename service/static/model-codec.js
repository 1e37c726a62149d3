// The compact rendering model codec of texture_library/model_codec.py, in the browser: a whole payload (b"HLM2") or
// a delta (b"HLD3") against the body of a payload held → the served model's JSON document (the schema the render
// worklet reads), its source version and its body (the base of the next delta).
//
// Same layout, same arithmetic: LSFs are the running sums of GAP_FLOOR_RAD · exp(code · ln(1 + 2^(3 − bits))) in
// the encoder's order (Math.exp and numpy's exp may differ in the last bit: the parity test allows 1e-12
// relative); √variance and gain are float16, squared as doubles; speeds, forces, μ and the ranges float32.
// Inflating uses the browser's DecompressionStream("deflate") (zlib), read in chunks and cut off at MAX_BODY_BYTES;
// a delta's base is named by the first 8 bytes of the SHA-256 of its body (crypto.subtle: a secure page, as the
// AudioWorklet needs). Every problem throws an Error naming it; nothing half-decoded is returned.
"use strict";

const hapticlinkCodec = (() => {
  const MAGIC = "HLM2", OLD_MAGIC = "HLM1", DELTA_MAGIC = "HLD3";
  const GAP_FLOOR_RAD = 1e-6;
  const MAX_BODY_BYTES = 512 * 1024;  // texture_library.render_model.MAX_RENDER_MODEL_BYTES
  const DELTA_HEAD = 12;

  const tagOf = (bytes) => String.fromCharCode(...bytes.subarray(0, 4));
  const hex = (bytes) => Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");

  async function inflate(bytes, what) {
    const reader = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate")).getReader();
    const parts = [];
    let size = 0;
    try {
      for (;;) {
        const {done, value} = await reader.read();
        if (done) break;
        size += value.length;
        if (size > MAX_BODY_BYTES) { reader.cancel(); throw new Error(`${what}: the body inflates past ${MAX_BODY_BYTES} bytes`); }
        parts.push(value);
      }
    } catch (err) {
      if (String(err.message || err).includes("inflates past")) throw err;
      throw new Error(`${what}: the body does not inflate (${err.message || err})`);
    }
    const out = new Uint8Array(size);
    let at = 0;
    for (const p of parts) { out.set(p, at); at += p.length; }
    return out;
  }

  /** The inflated body of a whole payload (Uint8Array). */
  async function body(payload) {
    const tag = tagOf(payload);
    if (tag === OLD_MAGIC) throw new Error(`compact rendering model of the old layout ${OLD_MAGIC} (uniform LSF codes); this client reads ${MAGIC}`);
    if (tag !== MAGIC) throw new Error(`not a compact rendering model (starts ${JSON.stringify(tag)}, expected ${MAGIC})`);
    return inflate(payload.subarray(4), "compact rendering model");
  }

  /** The 8-byte digest a delta names its base by, as hex. */
  async function digest(bodyBytes) {
    return hex(new Uint8Array(await crypto.subtle.digest("SHA-256", bodyBytes)).subarray(0, 8));
  }

  /** The base digest (hex) a delta names. */
  function deltaBase(payload) {
    if (payload.length < DELTA_HEAD || tagOf(payload) !== DELTA_MAGIC) {
      throw new Error(`not a compact rendering model delta (starts ${JSON.stringify(tagOf(payload))}, expected ${DELTA_MAGIC})`);
    }
    return hex(payload.subarray(4, DELTA_HEAD));
  }

  function half(h) {  // IEEE 754 binary16 → double, exactly
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, f = h & 0x3ff;
    if (e === 0) return s * f * 2 ** -24;
    if (e === 31) return f ? NaN : s * Infinity;
    return s * (1 + f / 1024) * 2 ** (e - 15);
  }

  /** A body → {source, model}: model is the served JSON document (model_version: the source version). */
  function parse(b) {
    const view = new DataView(b.buffer, b.byteOffset, b.byteLength);
    let pos = 0;
    const need = (n) => {
      if (pos + n > b.length) throw new Error(`compact rendering model: truncated at byte ${pos} (needs ${n} more)`);
      const at = pos; pos += n; return at;
    };
    const u8 = () => view.getUint8(need(1));
    const u16 = () => view.getUint16(need(2), true);
    const text = () => { const n = u8(), at = need(n); return new TextDecoder("utf-8", {fatal: true}).decode(b.subarray(at, at + n)); };
    const f32s = (n) => { const at = need(4 * n); return Array.from({length: n}, (_, i) => view.getFloat32(at + 4 * i, true)); };
    const f16s = (n) => { const at = need(2 * n); return Array.from({length: n}, (_, i) => half(view.getUint16(at + 2 * i, true))); };
    const bits = u8(), m = u16(), p = u16(), q = u16(), t = u16(), flags = u8();
    const id = text(), name = text();
    const source = hex(b.subarray(need(8), pos));
    const rate = view.getFloat64(need(8), true);
    const [mu, maxSpeed, maxForce] = f32s(3);
    let surface = null;
    if (flags & 1) surface = {bump_height_mm: view.getFloat64(need(8), true), bump_period_mm: view.getFloat64(need(8), true)};
    const speeds = f32s(m), forces = f32s(m), std = f16s(m), gain = f16s(m);
    const wide = m > 255, triAt = need(3 * t * (wide ? 2 : 1));
    const triangles = Array.from({length: t}, (_, k) => [0, 1, 2].map((j) =>
      wide ? view.getUint16(triAt + 2 * (3 * k + j), true) : view.getUint8(triAt + 3 * k + j)));
    if (!(bits >= 4 && bits <= 15)) throw new Error(`compact rendering model: LSF bits ${bits} outside [4, 15]`);
    const step = Math.log1p(2 ** (3 - bits));
    const lsf = (order) => {
      const at = need(2 * m * order);
      return Array.from({length: m}, (_, r) => {
        const row = new Array(order);
        let decoded = 0;  // the encoder's order of additions
        for (let j = 0; j < order; j++) {
          decoded = decoded + GAP_FLOOR_RAD * Math.exp(view.getUint16(at + 2 * (r * order + j), true) * step);
          row[j] = decoded;
        }
        return row;
      });
    };
    const ar = lsf(p), ma = lsf(q);
    let taps = null;
    if (flags & 2) {
      const k = u8(), n = u16();
      const tapSpeeds = f32s(k), samples = f16s(k * n);
      taps = {speeds_mm_s: tapSpeeds, accel: Array.from({length: k}, (_, i) => samples.slice(i * n, (i + 1) * n))};
    }
    if (pos !== b.length) throw new Error(`compact rendering model: ${b.length - pos} unexpected bytes at the end`);
    const model = {
      schema: "hapticlink.render-model", schema_version: 1, id, model_version: source, name, rate_hz: rate,
      speeds_mm_s: speeds, forces_n: forces, triangles, ar_lsf: ar, ma_lsf: ma,
      variance: std.map((s) => s * s), gain, mu, max_speed_mm_s: maxSpeed, max_force_n: maxForce, surface, taps,
    };
    return {source, model};
  }

  /** A whole payload (Uint8Array) → {source, model, body}. */
  async function decode(payload) {
    const b = await body(payload);
    return {...parse(b), body: b};
  }

  /** A delta and the body of the base it was made against → {source, model, body}. */
  async function decodeDelta(payload, base) {
    const named = deltaBase(payload), held = await digest(base);
    if (named !== held) throw new Error(`the delta was made against base ${named}, not the one held (${held})`);
    const diff = await inflate(payload.subarray(DELTA_HEAD), "compact rendering model delta");
    const b = new Uint8Array(diff.length);
    for (let i = 0; i < diff.length; i++) b[i] = (diff[i] + (i < base.length ? base[i] : 0)) & 0xff;
    return {...parse(b), body: b};
  }

  return {decode, decodeDelta, deltaBase, digest, body};
})();
