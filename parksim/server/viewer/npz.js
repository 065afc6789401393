// Reads the uncompressed .npz that GET /render returns (numpy.savez): a zip of stored .npy entries.
// Only what the render reply holds is supported: little-endian uint8, float32 and unicode arrays in C order.

const SIG_EOCD = 0x06054b50, SIG_EOCD64_LOCATOR = 0x07064b50, SIG_CENTRAL = 0x02014b50, SIG_LOCAL = 0x04034b50;
const MAX32 = 0xffffffff, MAX16 = 0xffff;

function fail(msg) { throw new Error(`render reply is not a readable npz: ${msg}`); }

function u64(view, at) {
  const v = view.getBigUint64(at, true);
  if (v > BigInt(Number.MAX_SAFE_INTEGER)) fail("a zip64 size is too large");
  return Number(v);
}

// Where the central directory starts and how many entries it has (zip64 end records included).
function centralDirectory(view) {
  let end = -1;
  for (let at = view.byteLength - 22; at >= Math.max(0, view.byteLength - 22 - MAX16); at--) {
    if (view.getUint32(at, true) === SIG_EOCD) { end = at; break; }
  }
  if (end < 0) fail("no end-of-central-directory record");
  let count = view.getUint16(end + 10, true), offset = view.getUint32(end + 16, true);
  if ((count === MAX16 || offset === MAX32) && end >= 20 && view.getUint32(end - 20, true) === SIG_EOCD64_LOCATOR) {
    const record = u64(view, end - 12);
    count = u64(view, record + 32);
    offset = u64(view, record + 48);
  }
  return { count, offset };
}

// Sizes and local-header offset of a central entry, from its zip64 extra field where a 32-bit field is saturated.
function entrySizes(view, at, nameLen, extraLen) {
  const sizes = { size: view.getUint32(at + 24, true), compressed: view.getUint32(at + 20, true),
                  local: view.getUint32(at + 42, true) };
  let pos = at + 46 + nameLen;
  const stop = pos + extraLen;
  while (pos + 4 <= stop) {
    const id = view.getUint16(pos, true), len = view.getUint16(pos + 2, true);
    if (id === 0x0001) {
      let field = pos + 4;
      for (const key of ["size", "compressed", "local"]) {
        if (sizes[key] === MAX32) { sizes[key] = u64(view, field); field += 8; }
      }
    }
    pos += 4 + len;
  }
  return sizes;
}

// name -> [start, end) byte range of each stored entry's data.
function zipEntries(buffer) {
  const view = new DataView(buffer);
  const { count, offset } = centralDirectory(view);
  const entries = new Map();
  let at = offset;
  for (let i = 0; i < count; i++) {
    if (view.getUint32(at, true) !== SIG_CENTRAL) fail("bad central directory entry");
    const method = view.getUint16(at + 10, true);
    const nameLen = view.getUint16(at + 28, true), extraLen = view.getUint16(at + 30, true);
    const commentLen = view.getUint16(at + 32, true);
    const name = new TextDecoder().decode(new Uint8Array(buffer, at + 46, nameLen));
    if (method !== 0) fail(`entry ${name} is compressed (method ${method}); only stored entries are read`);
    const { size, local } = entrySizes(view, at, nameLen, extraLen);
    if (view.getUint32(local, true) !== SIG_LOCAL) fail(`bad local header for ${name}`);
    const start = local + 30 + view.getUint16(local + 26, true) + view.getUint16(local + 28, true);
    if (start + size > buffer.byteLength) fail(`entry ${name} runs past the end of the reply`);
    entries.set(name, [start, start + size]);
    at += 46 + nameLen + extraLen + commentLen;
  }
  return entries;
}

// One .npy file -> { dtype, shape, data } (data: Uint8Array, Float32Array, or a string for a 0-d unicode array).
function parseNpy(buffer, start, end) {
  const bytes = new Uint8Array(buffer, start, end - start);
  if (bytes[0] !== 0x93 || String.fromCharCode(...bytes.subarray(1, 6)) !== "NUMPY") fail("an entry is not .npy");
  const view = new DataView(buffer, start);
  const major = bytes[6];
  const headerLen = major === 1 ? view.getUint16(8, true) : view.getUint32(8, true);
  const dataStart = (major === 1 ? 10 : 12) + headerLen;
  const header = new TextDecoder().decode(bytes.subarray(dataStart - headerLen, dataStart));
  const descr = /'descr':\s*'([^']*)'/.exec(header), shapeText = /'shape':\s*\(([^)]*)\)/.exec(header);
  if (!descr || !shapeText || /'fortran_order':\s*True/.test(header)) fail(`unsupported .npy header ${header}`);
  const shape = shapeText[1].split(",").map((s) => s.trim()).filter(Boolean).map(Number);
  const count = shape.reduce((a, b) => a * b, 1);
  const from = start + dataStart;
  const dtype = descr[1];
  if (dtype === "|u1") return { dtype, shape, data: new Uint8Array(buffer, from, count) };
  if (dtype === "<f4") return { dtype, shape, data: new Float32Array(buffer.slice(from, from + 4 * count)) };
  const unicode = /^<U(\d+)$/.exec(dtype);
  if (unicode && count === 1) {
    const points = new Uint32Array(buffer.slice(from, from + 4 * Number(unicode[1])));
    const used = points.indexOf(0);
    return { dtype, shape, data: String.fromCodePoint(...(used < 0 ? points : points.subarray(0, used))) };
  }
  return fail(`unsupported dtype ${dtype}`);
}

// The arrays of an npz reply by key ("images/front", "depth/front", "bev", "meta"), .npy suffix dropped.
export function parseNpz(buffer) {
  const arrays = new Map();
  for (const [name, [start, end]] of zipEntries(buffer)) arrays.set(name.replace(/\.npy$/, ""), parseNpy(buffer, start, end));
  return arrays;
}
