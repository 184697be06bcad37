// The service's REST API as the viewer uses it: JSON requests, problem+json errors, NDJSON streams, npz
// answers and wire arrays ({dtype, shape, data: base64 of little-endian bytes}).

/** An API error: the problem+json document the service answered with (RFC 7807). */
export class ApiError extends Error {
  constructor(problem) {
    super(problem.detail || problem.title || `HTTP ${problem.status}`);
    this.problem = problem;
  }
}

async function problemOf(response) {
  const text = await response.text();
  try {
    const doc = JSON.parse(text);
    if (doc && typeof doc.detail === "string") return doc;
  } catch (_) {
    // not JSON: a proxy's page or an empty body; shown as the status line below
  }
  return { status: response.status, title: response.statusText, detail: text.slice(0, 300) || "no detail" };
}

/** A fetch() answer, or ApiError for every answer that is not 2xx. */
export async function answered(pending) {
  const response = await pending;
  if (!response.ok) throw new ApiError(await problemOf(response));
  return response;
}

/** fetch() that throws ApiError for every answer that is not 2xx. */
export async function call(path, init = {}) {
  return answered(fetch(path, init));
}

export async function getJSON(path) {
  return (await call(path)).json();
}

/** POST a JSON body; the answer as an ArrayBuffer. */
export async function postJSON(path, body) {
  const response = await call(path, {
    method: "POST",
    headers: { "content-type": "application/json" },
    body: JSON.stringify(body),
  });
  return response.arrayBuffer();
}

/**
 * POST a form and read its NDJSON stream: onEvent(event) for each progress and chunk event; resolves with
 * the result event; an error event rejects with its problem.
 */
export async function stream(path, form, onEvent, signal) {
  const response = await call(path, {
    method: "POST",
    headers: { accept: "application/x-ndjson" },
    body: form,
    signal,
  });
  const reader = response.body.getReader();
  const decoder = new TextDecoder();
  let buffered = "";
  let result = null;
  const handle = (line) => {
    if (!line.trim()) return;
    const event = JSON.parse(line);
    if (event.event === "error") throw new ApiError(event);
    if (event.event === "result") result = event;
    onEvent(event);
  };
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    buffered += decoder.decode(value, { stream: true });
    const lines = buffered.split("\n");
    buffered = lines.pop();
    lines.forEach(handle);
  }
  handle(buffered);
  if (!result) throw new ApiError({ status: 502, title: "No result", detail: "the stream ended without a result" });
  return result;
}

const TYPED = {
  "<f4": Float32Array, "<f8": Float64Array, "<i4": Int32Array, "<i8": BigInt64Array, "|b1": Uint8Array,
  "<u4": Uint32Array, "|u1": Uint8Array, float32: Float32Array, float64: Float64Array, int32: Int32Array,
  int64: BigInt64Array, bool: Uint8Array,
};

function npyArray(bytes, offset) {
  // .npy: magic "\x93NUMPY", version, header length (2 bytes in 1.0, 4 bytes in 2.0+), a Python dict header
  const view = new DataView(bytes.buffer, bytes.byteOffset);
  const major = bytes[offset + 6];
  const headerLength = major === 1 ? view.getUint16(offset + 8, true) : view.getUint32(offset + 8, true);
  const start = offset + (major === 1 ? 10 : 12);
  const header = new TextDecoder().decode(bytes.subarray(start, start + headerLength));
  const descr = /'descr':\s*'([^']+)'/.exec(header)[1];
  const shape = /'shape':\s*\(([^)]*)\)/.exec(header)[1].split(",").filter((s) => s.trim()).map(Number);
  const count = shape.reduce((a, b) => a * b, 1);
  const dataStart = start + headerLength;
  if (descr.startsWith("<U")) {
    const width = Number(descr.slice(2));
    const codes = new Uint32Array(bytes.slice(dataStart, dataStart + count * width * 4).buffer);
    const strings = [];
    for (let i = 0; i < count; i++) {
      strings.push(String.fromCodePoint(...codes.subarray(i * width, (i + 1) * width).filter((c) => c)));
    }
    return { value: { dtype: descr, shape, data: strings }, end: dataStart + count * width * 4 };
  }
  const Typed = TYPED[descr];
  if (!Typed) throw new Error(`unsupported npy dtype ${descr}`);
  const size = count * Typed.BYTES_PER_ELEMENT;
  // a copy: typed arrays need an aligned offset, and the zip's entries are not aligned
  const data = new Typed(bytes.slice(dataStart, dataStart + size).buffer);
  return { value: { dtype: descr, shape, data }, end: dataStart + size };
}

/**
 * The arrays of an uncompressed .npz (numpy.savez; zip64 headers too): {name: {dtype, shape, data}}, data a
 * typed array (or strings for unicode arrays). Entries are read in order from their local headers.
 */
export function parseNpz(buffer) {
  const bytes = new Uint8Array(buffer);
  const view = new DataView(buffer);
  const arrays = {};
  let offset = 0;
  while (offset + 30 <= bytes.length && view.getUint32(offset, true) === 0x04034b50) {
    if (view.getUint16(offset + 8, true) !== 0) throw new Error("compressed npz entries are not supported");
    const nameLength = view.getUint16(offset + 26, true);
    const extraLength = view.getUint16(offset + 28, true);
    const name = new TextDecoder().decode(bytes.subarray(offset + 30, offset + 30 + nameLength));
    const { value, end } = npyArray(bytes, offset + 30 + nameLength + extraLength);
    arrays[name.replace(/\.npy$/, "")] = value;
    offset = end;
    if (view.getUint32(offset, true) === 0x08074b50) offset += 16; // a data descriptor (signature, crc, sizes)
  }
  return arrays;
}

/** A wire array as {dtype, shape, data: typed array}. */
export function wireArray(array) {
  const binary = atob(array.data);
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  const Typed = TYPED[array.dtype];
  return { dtype: array.dtype, shape: array.shape, data: new Typed(bytes.buffer) };
}

/** base64 text as a Blob (the upgrade's files). */
export function base64Blob(text, type = "application/octet-stream") {
  const binary = atob(text);
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return new Blob([bytes], { type });
}
