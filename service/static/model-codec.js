// The compact rendering model codec of texture_library/model_codec.py, in the browser: a whole payload (b"HLM3") or
// a delta (b"HLD3") against the body of a payload held → the served model's JSON document (the schema the render
// worklet reads), its source version and its body (the base of the next delta).
//
// Same layout (a 15-byte head giving every section's length; arrays in byte planes; a delta differenced section by
// section), same arithmetic: LSFs are the running sums of GAP_FLOOR_RAD · exp(code · ln(1 + 2^(3 − bits))) in
// the encoder's order (Math.exp and numpy's exp may differ in the last bit: the parity test allows 1e-12
// relative); √variance and gain are float16, squared as doubles; speeds, forces, μ and the ranges float32.
// Inflating uses the browser's DecompressionStream("deflate") (zlib), read in chunks and cut off at MAX_BODY_BYTES;
// a delta's base is named by the first 8 bytes of the SHA-256 of its body (crypto.subtle: a secure page, as the
// AudioWorklet needs). Every problem throws an Error naming it; nothing half-decoded is returned.
"use strict";

const hapticlinkCodec = (() => {
  const MAGIC = "HLM3", DELTA_MAGIC = "HLD3";
  const OLD_MAGICS = {HLM1: "uniform LSF codes", HLM2: "no section head, no taps"};
  const HEAD = 15;  // u8 bits, u16 m, u16 p, u16 q, u16 t, u8 flags, u8 id length, u8 name length, u8 k, u16 n
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
    if (tag in OLD_MAGICS) throw new Error(`compact rendering model of the old layout ${tag} (${OLD_MAGICS[tag]}); this client reads ${MAGIC}`);
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

  function head(b) {
    if (b.length < HEAD) throw new Error(`compact rendering model: a body is at least ${HEAD} bytes`);
    const v = new DataView(b.buffer, b.byteOffset, HEAD);
    return {bits: v.getUint8(0), m: v.getUint16(1, true), p: v.getUint16(3, true), q: v.getUint16(5, true),
            t: v.getUint16(7, true), flags: v.getUint8(9), idLen: v.getUint8(10), nameLen: v.getUint8(11),
            k: v.getUint8(12), n: v.getUint16(13, true)};
  }

  /** The lengths of a body's sections after its head (model_codec._sections). */
  function sections(h) {
    const width = h.m > 255 ? 2 : 1;
    return [h.idLen, h.nameLen, 8, 20, h.flags & 1 ? 16 : 0, 4 * h.m, 4 * h.m, 2 * h.m, 2 * h.m, 3 * h.t * width,
            4 * h.k, 2 * h.k * h.n, 2 * h.m * h.p, 2 * h.m * h.q];
  }

  /** count little-endian elements of `width` bytes from byte planes → a DataView over them, interleaved. */
  function unplane(raw, width, count) {
    const out = new Uint8Array(width * count);
    for (let j = 0; j < width; j++) for (let i = 0; i < count; i++) out[i * width + j] = raw[j * count + i];
    return new DataView(out.buffer);
  }

  /** A body → {source, model}: model is the served JSON document (model_version: the source version). */
  function parse(b) {
    const h = head(b);
    if (!(h.bits >= 4 && h.bits <= 15)) throw new Error(`compact rendering model: LSF bits ${h.bits} outside [4, 15]`);
    let pos = HEAD;
    const take = (n) => {
      if (pos + n > b.length) throw new Error(`compact rendering model: truncated at byte ${pos} (needs ${n} more)`);
      pos += n; return b.subarray(pos - n, pos);
    };
    const text = (n) => new TextDecoder("utf-8", {fatal: true}).decode(take(n));
    const array = (width, count, read) => {
      const v = unplane(take(width * count), width, count);
      return Array.from({length: count}, (_, i) => read(v, i * width));
    };
    const f32 = (v, at) => v.getFloat32(at, true), f16 = (v, at) => half(v.getUint16(at, true));
    const u16 = (v, at) => v.getUint16(at, true), u8 = (v, at) => v.getUint8(at);
    const {m, p, q, t, k, n} = h;
    const id = text(h.idLen), name = text(h.nameLen);
    const source = hex(take(8));
    const scalars = new DataView(b.buffer, b.byteOffset + pos, 20); take(20);
    const rate = scalars.getFloat64(0, true), mu = scalars.getFloat32(8, true);
    const maxSpeed = scalars.getFloat32(12, true), maxForce = scalars.getFloat32(16, true);
    let surface = null;
    if (h.flags & 1) {
      const v = new DataView(b.buffer, b.byteOffset + pos, 16); take(16);
      surface = {bump_height_mm: v.getFloat64(0, true), bump_period_mm: v.getFloat64(8, true)};
    }
    const speeds = array(4, m, f32), forces = array(4, m, f32), std = array(2, m, f16), gain = array(2, m, f16);
    const tri = m > 255 ? array(2, 3 * t, u16) : array(1, 3 * t, u8);
    const triangles = Array.from({length: t}, (_, i) => tri.slice(3 * i, 3 * i + 3));
    const tapSpeeds = array(4, k, f32), samples = array(2, k * n, f16);
    const step = Math.log1p(2 ** (3 - h.bits));
    const lsf = (order) => {
      const codes = array(2, m * order, u16);
      return Array.from({length: m}, (_, r) => {
        const row = new Array(order);
        let decoded = 0;  // the encoder's order of additions
        for (let j = 0; j < order; j++) {
          decoded = decoded + GAP_FLOOR_RAD * Math.exp(codes[r * order + j] * step);
          row[j] = decoded;
        }
        return row;
      });
    };
    const ar = lsf(p), ma = lsf(q);
    if (pos !== b.length) throw new Error(`compact rendering model: ${b.length - pos} unexpected bytes at the end`);
    const taps = h.flags & 2
      ? {speeds_mm_s: tapSpeeds, accel: Array.from({length: k}, (_, i) => samples.slice(i * n, (i + 1) * n))}
      : null;
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
    // section by section (model_codec._difference): the head first, then each section against the base's same one
    const b = new Uint8Array(diff.length);
    const add = (at, size, baseAt, baseSize) => {
      for (let i = 0; i < size; i++) b[at + i] = (diff[at + i] + (i < baseSize ? base[baseAt + i] : 0)) & 0xff;
    };
    if (diff.length < HEAD) throw new Error("compact rendering model delta: shorter than a head");
    add(0, HEAD, 0, Math.min(HEAD, base.length));
    const mine = sections(head(b)), theirs = sections(head(base));
    let at = HEAD, baseAt = HEAD;
    for (let s = 0; s < mine.length; s++) {
      if (at + mine[s] > diff.length) throw new Error(`compact rendering model delta: malformed (ends at ${diff.length}, needs ${at + mine[s]})`);
      add(at, mine[s], baseAt, Math.max(0, Math.min(theirs[s], base.length - baseAt)));
      at += mine[s]; baseAt += theirs[s];
    }
    if (at !== diff.length) throw new Error(`compact rendering model delta: malformed (${diff.length - at} bytes after the last section)`);
    return {...parse(b), body: b};
  }

  return {decode, decodeDelta, deltaBase, digest, body};
})();
