// spk2img viewer: upload a spike stream to POST v1/reconstruct, read the response as it streams
// (fetch + ReadableStream), parse its records (docs/service.md, "Response framing") and show the
// frames one by one. No build step, no library, nothing fetched from elsewhere (docs/viewer.md).
"use strict";

(() => {
  const OCTET = "application/octet-stream";
  // The served network's window in frames: GET v1/models says it (its geometry), before any run.
  let netFrames = null;
  // A browser uploads the whole body before it reads the answer, so the service holds the frames
  // for it: up to response_buffer_bytes (32 MiB by default) for a Content-Length upload, else 413.
  // The page asks for at most this many bytes of frames a request and splits larger plans;
  // ?budget=BYTES in the page's URL sets it (a service run with a smaller buffer).
  const RESPONSE_BUDGET = Number(new URLSearchParams(location.search).get("budget")) || 16 * 1024 * 1024;
  const FRAME_RECORD_OVERHEAD = 28; // tag, length, centre, height, width, format
  const MAX_CENTRES_PER_REQUEST = 1000; // keeps a centres= list far under the 8 KiB query limit
  const TFI_CENTRES_PER_REQUEST = 16; // TFI holds its centres until every pixel fires again
  const BUSY_RETRIES = 10;
  const FILMSTRIP_THUMB = 104; // px a thumbnail takes in the strip: 96 + borders + gap
  const YIELD_MS = 30; // long loops give the page back this often

  const $ = (id) => document.getElementById(id);
  const ui = {
    form: $("form"), file: $("file"), fileInfo: $("file-info"), height: $("height"),
    width: $("width"), preset: $("preset"), method: $("method"), quality: $("quality"),
    binning: $("binning"), binningHint: $("binning-hint"), binningNa: $("binning-na"),
    window: $("window"), gamma: $("gamma"), useStride: $("use-stride"), stride: $("stride"),
    useCenters: $("use-centers"), centers: $("centers"), compare: $("compare"), run: $("run"),
    stop: $("stop"), progress: $("progress"), status: $("status"), error: $("error"),
    panes: $("panes"), paneB: $("pane-b"), canvasA: $("canvas-a"), canvasB: $("canvas-b"),
    captionA: $("caption-a"), captionB: $("caption-b"), slider: $("slider"), prev: $("prev"),
    next: $("next"), frameLabel: $("frame-label"), follow: $("follow"), zoom: $("zoom"),
    layoutBox: $("layout-box"), layout: $("layout"), toggle: $("toggle"),
    filmstrip: $("filmstrip"), downloadPng: $("download-png"), downloadNpz: $("download-npz"),
    downloadNote: $("download-note"), serviceStatus: $("service-status"),
  };

  const state = {
    source: null, // {blob, name, stem, kind, shape}: the stream as .dat bytes
    runs: [], // run A (and B when comparing): {label, method, frames: Map, centres: [], ...}
    index: 0, // position in run A's centres
    showB: false, // toggle layout: which run is shown
    abort: null,
    loading: false,
    drawQueued: false,
  };

  class ServiceError extends Error {
    constructor(status, detail) {
      super(`${status}: ${detail}`);
      this.status = status;
      this.detail = detail;
    }
  }

  // ---------------------------------------------------------------- small helpers

  const sleep = (ms, signal) => new Promise((resolve, reject) => {
    const timer = setTimeout(resolve, ms);
    signal?.addEventListener("abort", () => {
      clearTimeout(timer);
      reject(new DOMException("stopped", "AbortError"));
    }, { once: true });
  });
  const nextTick = () => new Promise((resolve) => setTimeout(resolve, 0));

  function formatBytes(n) {
    if (n < 1024) return `${n} B`;
    if (n < 1024 * 1024) return `${(n / 1024).toFixed(1)} KiB`;
    return `${(n / 1024 / 1024).toFixed(1)} MiB`;
  }

  function ascii(bytes, start, length) {
    let text = "";
    for (let i = start; i < start + length; i++) text += String.fromCharCode(bytes[i]);
    return text;
  }

  function concat(parts, total) {
    const out = new Uint8Array(total ?? parts.reduce((n, p) => n + p.length, 0));
    let at = 0;
    for (const part of parts) {
      out.set(part, at);
      at += part.length;
    }
    return out;
  }

  function setStatus(text) { ui.status.textContent = text; }

  function setProgress(fraction) {
    if (fraction === null) ui.progress.removeAttribute("value"); // indeterminate
    else ui.progress.value = Math.max(0, Math.min(1, fraction));
  }

  function showError(text) {
    ui.error.textContent = text;
    ui.error.hidden = false;
  }

  function clearError() {
    ui.error.textContent = "";
    ui.error.hidden = true;
  }

  // Binning applies to net with quality best only: the service refuses it elsewhere (422).
  function binnable() {
    return ui.method.value === "net" && ui.quality.value === "best";
  }

  // The stream frames a network window spans: the network's frames merged K at a time, plus one
  // when K is even (so that it stays centred).
  function netWindow(binning) {
    if (netFrames === null) throw new Error("the service has not said its model's window yet: wait until it is ready");
    return (netFrames * binning) | 1;
  }

  function positiveInt(input, name) {
    const value = Number(input.value);
    if (!Number.isInteger(value) || value < 1) throw new Error(`${name} must be a positive whole number`);
    return value;
  }

  // ---------------------------------------------------------------- the response framing

  // record := tag (4 ASCII) | length (uint32 LE) | payload. Chunks are kept as they come and
  // joined only once a whole record is there.
  class RecordParser {
    constructor() {
      this.parts = [];
      this.total = 0;
    }

    feed(chunk) {
      this.parts.push(chunk);
      this.total += chunk.length;
      const records = [];
      for (;;) {
        if (this.total < 8) break;
        const head = this.parts[0].length >= 8 ? this.parts[0] : this.flatten();
        const length = new DataView(head.buffer, head.byteOffset, 8).getUint32(4, true);
        if (this.total < 8 + length) break;
        const bytes = this.parts.length === 1 ? this.parts[0] : this.flatten();
        records.push(parseRecord(ascii(bytes, 0, 4), bytes.subarray(8, 8 + length)));
        const rest = bytes.subarray(8 + length);
        this.parts = rest.length ? [rest] : [];
        this.total = rest.length;
      }
      return records;
    }

    flatten() {
      const whole = concat(this.parts, this.total);
      this.parts = [whole];
      return whole;
    }
  }

  function parseRecord(tag, payload) {
    const view = new DataView(payload.buffer, payload.byteOffset, payload.length);
    if (tag === "FRAM") {
      const height = view.getUint32(8, true);
      const width = view.getUint32(12, true);
      return {
        tag,
        centre: Number(view.getBigInt64(0, true)),
        height,
        width,
        format: ascii(payload, 16, 4),
        data: payload.slice(20), // a copy: the parser's buffer is reused
      };
    }
    if (tag === "ERRO" || tag === "DONE") {
      return { tag, ...JSON.parse(new TextDecoder().decode(payload)) };
    }
    throw new Error(`the response holds an unknown record ${JSON.stringify(tag)}`);
  }

  // ---------------------------------------------------------------- reading the stream file

  // .npy: (T, H, W) 0/1, upright, time first -> .dat bytes (rows bottom first, bits LSB first).
  function parseNpy(bytes, where) {
    if (bytes.length < 10 || bytes[0] !== 0x93 || ascii(bytes, 1, 5) !== "NUMPY") {
      throw new Error(`${where}: not a .npy file`);
    }
    const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.length);
    const major = bytes[6];
    const headerLength = major === 1 ? view.getUint16(8, true) : view.getUint32(8, true);
    const start = (major === 1 ? 10 : 12) + headerLength;
    const header = ascii(bytes, major === 1 ? 10 : 12, headerLength);
    const descr = /'descr':\s*'([^']+)'/.exec(header)?.[1];
    const fortran = /'fortran_order':\s*True/.test(header);
    const shapeText = /'shape':\s*\(([^)]*)\)/.exec(header)?.[1] ?? "";
    const shape = shapeText.split(",").map((s) => s.trim()).filter(Boolean).map(Number);
    if (shape.length !== 3) {
      throw new Error(`${where}: a spike array must be (T, H, W), this one is (${shape.join(", ")})`);
    }
    if (fortran) throw new Error(`${where}: Fortran-ordered arrays are not supported; save it C-ordered`);
    const count = shape[0] * shape[1] * shape[2];
    const types = {
      u1: Uint8Array, b1: Uint8Array, i1: Int8Array, u2: Uint16Array, i2: Int16Array,
      u4: Uint32Array, i4: Int32Array, u8: BigUint64Array, i8: BigInt64Array,
      f4: Float32Array, f8: Float64Array,
    };
    const kind = descr?.slice(1);
    const Type = types[kind];
    if (!Type) throw new Error(`${where}: spike arrays of dtype ${descr} are not supported`);
    const size = Type.BYTES_PER_ELEMENT;
    if (start + count * size > bytes.length) throw new Error(`${where}: the file is cut short`);
    let raw = bytes.subarray(start, start + count * size);
    if (descr[0] === ">" && size > 1) { // big-endian: swap into a copy
      raw = raw.slice();
      for (let i = 0; i < raw.length; i += size) raw.subarray(i, i + size).reverse();
    }
    const aligned = (raw.byteOffset % size === 0) ? raw : raw.slice();
    const values = new Type(aligned.buffer, aligned.byteOffset, count);
    return { shape, dtype: descr, values, big: kind === "u8" || kind === "i8" };
  }

  async function packSpikes(array, where, onProgress) {
    const [frames, height, width] = array.shape;
    const perFrame = Math.ceil((height * width) / 8);
    const out = new Uint8Array(frames * perFrame);
    const { values } = array;
    const one = array.big ? 1n : 1;
    const zero = array.big ? 0n : 0;
    let last = performance.now();
    for (let t = 0; t < frames; t++) {
      const base = t * height * width;
      const outBase = t * perFrame;
      for (let r = 0; r < height; r++) {
        const src = base + r * width;
        const p0 = (height - 1 - r) * width; // .dat rows are stored bottom first
        for (let c = 0; c < width; c++) {
          const v = values[src + c];
          if (v === zero) continue;
          if (v !== one) {
            throw new Error(`${where}: value ${v} at frame ${t}, row ${r}, column ${c}: a spike array holds 0 and 1 only`);
          }
          const p = p0 + c;
          out[outBase + (p >> 3)] |= 1 << (p & 7);
        }
      }
      if (performance.now() - last > YIELD_MS) {
        onProgress(t + 1, frames);
        await nextTick();
        last = performance.now();
      }
    }
    return out;
  }

  async function inflateRaw(bytes) {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate-raw"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  // .npz: a zip of .npy files; the array is "spk" or "spikes", else the only one.
  async function npzArray(bytes, where) {
    const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.length);
    let end = -1;
    for (let i = bytes.length - 22; i >= Math.max(0, bytes.length - 65557); i--) {
      if (view.getUint32(i, true) === 0x06054b50) { end = i; break; }
    }
    if (end < 0) throw new Error(`${where}: not a readable .npz archive`);
    const entries = [];
    let at = view.getUint32(end + 16, true);
    for (let n = view.getUint16(end + 10, true); n > 0; n--) {
      if (view.getUint32(at, true) !== 0x02014b50) throw new Error(`${where}: a damaged .npz archive`);
      const nameLength = view.getUint16(at + 28, true);
      const extraLength = view.getUint16(at + 30, true);
      const commentLength = view.getUint16(at + 32, true);
      let size = view.getUint32(at + 20, true);
      let offset = view.getUint32(at + 42, true);
      const extraAt = at + 46 + nameLength;
      for (let e = extraAt; e < extraAt + extraLength; e += 4 + view.getUint16(e + 2, true)) {
        if (view.getUint16(e, true) !== 1) continue; // zip64: the sizes and offset in 64 bits
        let field = e + 4;
        const read = () => { const v = Number(view.getBigUint64(field, true)); field += 8; return v; };
        if (view.getUint32(at + 24, true) === 0xffffffff) read(); // the uncompressed size
        if (size === 0xffffffff) size = read();
        if (offset === 0xffffffff) offset = read();
      }
      entries.push({
        name: new TextDecoder().decode(bytes.subarray(at + 46, at + 46 + nameLength)),
        method: view.getUint16(at + 10, true), size, offset,
      });
      at += 46 + nameLength + extraLength + commentLength;
    }
    const named = entries.filter((e) => e.name === "spk.npy" || e.name === "spikes.npy");
    if (!named.length && entries.length !== 1) {
      throw new Error(`${where}: holds ${entries.map((e) => e.name).join(", ")}; expected a 'spk' array`);
    }
    const entry = named[0] ?? entries[0];
    const local = entry.offset;
    const dataAt = local + 30 + view.getUint16(local + 26, true) + view.getUint16(local + 28, true);
    let data = bytes.subarray(dataAt, dataAt + entry.size);
    if (entry.method === 8) data = await inflateRaw(data);
    else if (entry.method !== 0) throw new Error(`${where}: zip compression method ${entry.method} is not supported`);
    return parseNpy(data, `${where}:${entry.name}`);
  }

  async function loadFile(file) {
    state.source = null;
    clearError();
    const suffix = file.name.slice(file.name.lastIndexOf(".")).toLowerCase();
    const stem = file.name.slice(0, file.name.length - suffix.length) || "stream";
    if (suffix !== ".npy" && suffix !== ".npz") {
      state.source = { blob: file, name: file.name, stem, kind: "dat", shape: null };
      ui.height.disabled = ui.width.disabled = false;
      describeSource();
      updateButtons();
      return;
    }
    state.loading = true;
    updateButtons();
    try {
      setStatus(`reading ${file.name} (${formatBytes(file.size)})…`);
      setProgress(null);
      const bytes = new Uint8Array(await file.arrayBuffer());
      const array = suffix === ".npz" ? await npzArray(bytes, file.name) : parseNpy(bytes, file.name);
      const packed = await packSpikes(array, file.name, (t, total) => {
        setStatus(`packing ${file.name} to .dat bytes: frame ${t} of ${total}`);
        setProgress(t / total);
      });
      const [, height, width] = array.shape;
      ui.height.value = height;
      ui.width.value = width;
      ui.height.disabled = ui.width.disabled = true; // the array's shape says
      state.source = { blob: new Blob([packed]), name: file.name, stem, kind: suffix.slice(1), shape: array.shape };
      setStatus(`${file.name} ready`);
      setProgress(0);
    } catch (error) {
      showError(error.message);
      setStatus("");
      setProgress(0);
    } finally {
      state.loading = false;
      describeSource();
      updateButtons();
    }
  }

  function describeSource() {
    const source = state.source;
    if (!source) {
      ui.fileInfo.textContent = "no file chosen";
      return;
    }
    if (source.shape) {
      const [t, h, w] = source.shape;
      ui.fileInfo.textContent = `${source.name}: (${t}, ${h}, ${w}) spikes, sent as ` +
        `${formatBytes(source.blob.size)} of .dat bytes`;
      return;
    }
    const height = Number(ui.height.value);
    const width = Number(ui.width.value);
    const perFrame = Math.ceil((height * width) / 8);
    const size = source.blob.size;
    if (!(perFrame > 0)) ui.fileInfo.textContent = `${source.name}: ${formatBytes(size)}`;
    else if (size % perFrame === 0) {
      ui.fileInfo.textContent = `${source.name}: ${formatBytes(size)} = ${size / perFrame} frames of ${height}×${width}`;
    } else {
      ui.fileInfo.textContent = `${source.name}: ${formatBytes(size)}, not a whole number of ` +
        `${height}×${width} frames (${perFrame} bytes each): check the size`;
    }
  }

  // ---------------------------------------------------------------- planning the requests

  function readSettings() {
    const height = positiveInt(ui.height, "height");
    const width = positiveInt(ui.width, "width");
    const gamma = Number(ui.gamma.value);
    if (!(gamma > 0)) throw new Error("gamma must be a positive number");
    const byStride = ui.useStride.checked;
    const stride = byStride ? positiveInt(ui.stride, "stride") : null;
    const centers = byStride ? null : ui.centers.value.replace(/\s+/g, "");
    if (!byStride && !centers) throw new Error("give the centres, e.g. 40,80,120, or a stride");
    const binning = binnable() ? positiveInt(ui.binning, "binning") : 1;
    return { height, width, gamma, stride, centers, binning, window: Number(ui.window.value) };
  }

  // The requests for one method: one when its frames fit in RESPONSE_BUDGET (exactly the query
  // a user would send with curl), else batches of centres. For net and TFP a batch uploads only
  // the frames its windows need; TFI searches the whole stream, so its batches upload it all.
  function planRequests(run, settings, frameCount) {
    const { height, width, gamma, stride, centers } = settings;
    const base = { height, width, method: run.method, format: "uint8", gamma };
    if (run.method === "net") base.quality = run.quality;
    else base.window = settings.window;
    if (run.binning > 1) base.binning = run.binning; // binning=1 is the default: not sent
    const half = Math.floor((run.method === "net" ? netWindow(run.binning) : settings.window) / 2);
    const whole = { start: 0, end: null, offset: 0 }; // end null: the whole file
    const asked = stride ? { stride } : { centers };
    let wanted = null; // the centres, when the page can tell them (else the service says why not)
    const oddWindow = Number.isInteger(settings.window) && settings.window % 2 === 1;
    if (frameCount !== null && (run.method === "net" || oddWindow)) {
      if (stride) {
        wanted = [];
        for (let k = half; k + half < frameCount; k += stride) wanted.push(k);
      } else if (/^\d+(,\d+)*$/.test(centers)) {
        const list = centers.split(",").map(Number);
        const valid = list.every((k, i) => k >= half && k + half < frameCount && (i === 0 || k > list[i - 1]));
        if (valid) wanted = list;
      }
    }
    if (wanted !== null && wanted.length === 0) wanted = null; // too short: the service's 422
    run.expected = wanted ? wanted.length : null;
    let cap = Math.floor(RESPONSE_BUDGET / (FRAME_RECORD_OVERHEAD + height * width));
    cap = Math.max(1, Math.min(cap, run.method === "tfi" ? TFI_CENTRES_PER_REQUEST : MAX_CENTRES_PER_REQUEST));
    if (!wanted || wanted.length <= cap) return [{ query: { ...base, ...asked }, ...whole }];
    const requests = [];
    for (let i = 0; i < wanted.length; i += cap) {
      const group = wanted.slice(i, i + cap);
      if (run.method === "tfi") {
        requests.push({ query: { ...base, centers: group.join(",") }, ...whole });
        continue;
      }
      const start = group[0] - half;
      const end = group[group.length - 1] + half + 1;
      // with a stride, a slice from the batch's first window gives exactly its centres
      const which = stride ? { stride } : { centers: group.map((k) => k - start).join(",") };
      requests.push({ query: { ...base, ...which }, start, end, offset: start });
    }
    return requests;
  }

  // ---------------------------------------------------------------- talking to the service

  async function errorDetail(response) {
    const text = await response.text();
    try {
      const body = JSON.parse(text);
      if (typeof body.detail === "string") return body.detail;
      return JSON.stringify(body.detail ?? body);
    } catch {
      return text.trim() || response.statusText || "no detail";
    }
  }

  async function sendRequest(run, request, context) {
    const { blob, perFrame, signal, batch } = context;
    const body = request.end === null ? blob : blob.slice(request.start * perFrame, request.end * perFrame);
    const url = `v1/reconstruct?${new URLSearchParams(request.query)}`;
    for (let attempt = 0; ; attempt++) {
      setStatus(`${run.label}${batch}: uploading ${formatBytes(body.size)}…`);
      if (run.received === 0) setProgress(null);
      let response;
      try {
        response = await fetch(url, { method: "POST", body, headers: { "Content-Type": OCTET }, signal });
      } catch (error) {
        if (signal.aborted) throw error;
        throw new Error(`the request failed before the service answered (${error.message}): is the service still running?`);
      }
      if (response.status === 503 && attempt < BUSY_RETRIES) {
        const detail = await errorDetail(response);
        const wait = Math.max(1, Number(response.headers.get("Retry-After")) || 1);
        setStatus(`${run.label}: service busy (${detail}); trying again in ${wait} s`);
        await sleep(wait * 1000, signal);
        continue;
      }
      if (!response.ok) throw new ServiceError(response.status, await errorDetail(response));
      await readFrames(response, run, request.offset, batch);
      return;
    }
  }

  async function readFrames(response, run, offset, batch) {
    const reader = response.body.getReader();
    const parser = new RecordParser();
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      for (const record of parser.feed(value)) {
        if (record.tag === "FRAM") {
          if (record.format !== "u8  ") throw new Error(`unexpected frame format ${JSON.stringify(record.format)}`);
          addFrame(run, record.centre + offset, record);
          setStatus(`${run.label}${batch}: ${run.received}${run.expected ? ` of ${run.expected}` : ""} frames, ` +
            `${rate(run)} frames/s`);
        } else if (record.tag === "ERRO") {
          throw new ServiceError(record.status, record.detail);
        } else if (record.tag === "DONE") {
          return;
        }
      }
    }
    throw new Error("the response was cut: it ended without DONE or ERRO (the service stopped or the connection dropped)");
  }

  function rate(run) {
    const seconds = (performance.now() - run.started) / 1000;
    return seconds > 0 ? (run.received / seconds).toFixed(1) : "–";
  }

  function addFrame(run, centre, record) {
    run.height = record.height;
    run.width = record.width;
    if (!run.frames.has(centre)) run.centres.push(centre);
    run.frames.set(centre, record.data);
    run.received += 1;
    const total = state.runs.reduce((n, r) => n + (r.expected ?? 0), 0);
    const received = state.runs.reduce((n, r) => n + r.received, 0);
    setProgress(total ? received / total : null);
    if (run === state.runs[0] && ui.follow.checked) state.index = run.centres.length - 1;
    scheduleDraw();
  }

  function newRun(method, quality, tag, binning = 1) {
    const label = method === "net" ? `net (${quality}${binning > 1 ? `, binning ${binning}` : ""})` : method;
    return {
      tag, label, method, quality, binning, frames: new Map(), centres: [], received: 0,
      expected: null, height: 0, width: 0, done: false, error: null, started: performance.now(),
    };
  }

  async function reconstruct() {
    clearError();
    if (!state.source) {
      showError("choose a spike stream file first");
      return;
    }
    let settings;
    try {
      settings = readSettings();
    } catch (error) {
      showError(error.message);
      return;
    }
    const perFrame = Math.ceil((settings.height * settings.width) / 8);
    const blob = state.source.blob;
    const frameCount = blob.size % perFrame === 0 ? blob.size / perFrame : null;
    const compare = ui.compare.value;
    const runs = [newRun(ui.method.value, ui.quality.value, "A", settings.binning)];
    if (compare) runs.push(newRun(compare, "best", "B"));
    runs.forEach((run) => { run.settings = settings; });
    let plans;
    try {
      plans = runs.map((run) => planRequests(run, settings, frameCount));
    } catch (error) {
      showError(error.message); // e.g. the service has not said its model's window yet
      return;
    }
    state.runs = runs;
    state.index = 0;
    state.showB = false;
    state.gamma = settings.gamma;
    resetView();
    state.abort = new AbortController();
    updateButtons();
    const started = performance.now();
    try {
      for (const [i, run] of state.runs.entries()) {
        run.started = performance.now();
        const requests = plans[i];
        for (const [j, request] of requests.entries()) {
          const batch = requests.length > 1 ? ` (request ${j + 1} of ${requests.length})` : "";
          await sendRequest(run, request, { blob, perFrame, signal: state.abort.signal, batch });
        }
        run.done = true;
      }
      const frames = state.runs.map((r) => `${r.received} ${r.label}`).join(" and ");
      setStatus(`done: ${frames} frames in ${((performance.now() - started) / 1000).toFixed(1)} s`);
      setProgress(1);
    } catch (error) {
      if (error.name === "AbortError") {
        setStatus("stopped");
      } else {
        const run = state.runs.find((r) => !r.done);
        if (run) run.error = error.message;
        showError(error instanceof ServiceError
          ? `The service answered ${error.status}: ${error.detail}` : error.message);
        setStatus(`${run ? run.label : ""} failed`);
      }
      setProgress(0);
    } finally {
      state.abort = null;
      updateButtons();
      drawNow(); // now, not at the next animation frame: the frames that came show with the error
    }
  }

  // ---------------------------------------------------------------- showing the frames

  function resetView() {
    const comparing = state.runs.length > 1;
    ui.paneB.hidden = !comparing;
    ui.layoutBox.hidden = !comparing;
    ui.toggle.hidden = !comparing || ui.layout.value !== "toggle";
    ui.filmstrip.replaceChildren();
    drawNow();
  }

  function scheduleDraw() {
    if (state.drawQueued) return;
    state.drawQueued = true;
    requestAnimationFrame(() => {
      state.drawQueued = false;
      drawNow();
    });
  }

  function paint(canvas, run, centre, note = "") {
    const data = run?.frames.get(centre);
    canvas.dataset.centre = data ? String(centre) : "";
    canvas.dataset.method = run ? run.method : "";
    const ctx = canvas.getContext("2d");
    if (!data) { // a placeholder with a word on it
      ctx.fillStyle = "#1b1f27";
      ctx.fillRect(0, 0, canvas.width, canvas.height);
      ctx.fillStyle = "#8a93a6";
      ctx.font = `${Math.max(10, Math.round(canvas.height / 14))}px sans-serif`;
      ctx.textAlign = "center";
      ctx.textBaseline = "middle";
      ctx.fillText(note, canvas.width / 2, canvas.height / 2);
      return false;
    }
    if (canvas.width !== run.width || canvas.height !== run.height) {
      canvas.width = run.width;
      canvas.height = run.height;
    }
    const image = ctx.createImageData(run.width, run.height);
    const rgba = new Uint32Array(image.data.buffer);
    for (let i = 0; i < data.length; i++) rgba[i] = 0xff000000 | (data[i] * 0x010101); // little-endian ABGR
    ctx.putImageData(image, 0, 0);
    return true;
  }

  function drawNow() {
    const [a, b] = state.runs;
    const centres = a ? a.centres : [];
    const n = centres.length;
    state.index = Math.max(0, Math.min(state.index, n - 1));
    ui.slider.max = String(Math.max(0, n - 1));
    ui.slider.value = String(state.index);
    ui.slider.disabled = n < 2;
    const centre = n ? centres[state.index] : null;
    if (!a) {
      paint(ui.canvasA, null, null, "choose a spike stream and press Reconstruct");
      ui.captionA.textContent = "—";
      ui.frameLabel.textContent = "no frames";
    } else {
      paint(ui.canvasA, a, centre, state.abort ? "waiting for the first frame…" : "no frame");
      ui.captionA.textContent = `${a.label}` + (centre !== null ? `, centre ${centre}` : state.abort ? ", waiting for frames" : ", no frames");
      ui.frameLabel.textContent = n
        ? `frame ${state.index + 1} of ${n}${a.expected && a.expected !== n ? ` (${a.expected} coming)` : ""} · centre ${centre}`
        : state.abort ? "no frames yet" : "no frames";
    }
    if (b) {
      const waiting = state.abort !== null && !b.done && !b.error;
      const missing = centre === null ? "" : waiting ? `centre ${centre}: not yet` : `no frame at centre ${centre}`;
      const shown = paint(ui.canvasB, b, centre, missing);
      ui.captionB.textContent = `${b.label}` + (shown ? `, centre ${centre}` : missing ? `, ${missing}` : "");
      const toggled = ui.layout.value === "toggle";
      ui.panes.className = toggled ? "toggle" : "side";
      $("pane-a").classList.toggle("hidden-by-toggle", toggled && state.showB);
      ui.paneB.classList.toggle("hidden-by-toggle", toggled && !state.showB);
      ui.toggle.textContent = state.showB ? "show A" : "show B";
    } else {
      ui.panes.className = "side";
      $("pane-a").classList.remove("hidden-by-toggle");
    }
    applyZoom();
    drawFilmstrip(a, centres);
    $("gamma-shown").textContent = $("gamma-shown-2").textContent = String(state.gamma ?? ui.gamma.value);
    updateButtons();
  }

  function applyZoom() {
    for (const canvas of [ui.canvasA, ui.canvasB]) {
      const zoom = ui.zoom.value;
      canvas.classList.toggle("fit", zoom === "fit");
      canvas.style.width = zoom === "fit" ? "" : `${canvas.width * Number(zoom)}px`;
    }
  }

  // Only the thumbnails that fit in the strip exist, around the current frame: cheap however
  // many frames the run has.
  function drawFilmstrip(run, centres) {
    const strip = ui.filmstrip;
    if (!run || !centres.length) {
      strip.replaceChildren();
      return;
    }
    const slots = Math.max(1, Math.floor((strip.clientWidth || 800) / FILMSTRIP_THUMB));
    const first = Math.max(0, Math.min(state.index - Math.floor(slots / 2), centres.length - slots));
    const last = Math.min(centres.length, first + slots);
    while (strip.children.length > last - first) strip.lastChild.remove();
    while (strip.children.length < last - first) {
      const figure = document.createElement("figure");
      figure.append(document.createElement("canvas"), document.createElement("figcaption"));
      figure.addEventListener("click", () => goTo(Number(figure.dataset.index)));
      strip.append(figure);
    }
    for (let i = first; i < last; i++) {
      const figure = strip.children[i - first];
      const key = `${run.tag}:${centres[i]}:${run.started}`;
      figure.dataset.index = String(i);
      figure.classList.toggle("current", i === state.index);
      if (figure.dataset.key !== key) {
        figure.dataset.key = key;
        paint(figure.firstChild, run, centres[i]);
        figure.lastChild.textContent = String(centres[i]);
      }
    }
  }

  function goTo(index) {
    const n = state.runs[0]?.centres.length ?? 0;
    if (!n) return;
    state.index = Math.max(0, Math.min(index, n - 1));
    if (state.index < n - 1) ui.follow.checked = false; // stepping back stops following
    scheduleDraw();
  }

  // ---------------------------------------------------------------- downloads

  const CRC_TABLE = (() => {
    const table = new Uint32Array(256);
    for (let n = 0; n < 256; n++) {
      let c = n;
      for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
      table[n] = c >>> 0;
    }
    return table;
  })();

  function crc32(bytes, crc = 0) {
    let c = ~crc >>> 0;
    for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
    return ~c >>> 0;
  }

  async function zlib(bytes) {
    const stream = new Blob([bytes]).stream().pipeThrough(new CompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  function pngChunk(type, data) {
    const out = new Uint8Array(12 + data.length);
    const view = new DataView(out.buffer);
    view.setUint32(0, data.length);
    for (let i = 0; i < 4; i++) out[4 + i] = type.charCodeAt(i);
    out.set(data, 8);
    view.setUint32(8 + data.length, crc32(out.subarray(4, 8 + data.length)));
    return out;
  }

  // An 8-bit greyscale PNG of the display values (filter 0 on every row).
  async function encodePng(grey, width, height) {
    const raw = new Uint8Array(height * (width + 1));
    for (let r = 0; r < height; r++) raw.set(grey.subarray(r * width, (r + 1) * width), r * (width + 1) + 1);
    const header = new Uint8Array(13);
    const view = new DataView(header.buffer);
    view.setUint32(0, width);
    view.setUint32(4, height);
    header.set([8, 0, 0, 0, 0], 8); // 8 bits, greyscale, deflate, no filter, no interlace
    const signature = new Uint8Array([0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]);
    return concat([signature, pngChunk("IHDR", header), pngChunk("IDAT", await zlib(raw)), pngChunk("IEND", new Uint8Array(0))]);
  }

  // A zip with stored (uncompressed) entries; PNGs are compressed already.
  function zipFiles(files) {
    const parts = [];
    const directory = [];
    let offset = 0;
    const now = new Date();
    const time = (now.getHours() << 11) | (now.getMinutes() << 5) | (now.getSeconds() >> 1);
    const date = ((now.getFullYear() - 1980) << 9) | ((now.getMonth() + 1) << 5) | now.getDate();
    for (const { name, data } of files) {
      const nameBytes = new TextEncoder().encode(name);
      const crc = crc32(data);
      const local = new DataView(new ArrayBuffer(30));
      local.setUint32(0, 0x04034b50, true);
      local.setUint16(4, 20, true);
      local.setUint16(6, 0x0800, true); // UTF-8 names
      local.setUint16(10, time, true);
      local.setUint16(12, date, true);
      local.setUint32(14, crc, true);
      local.setUint32(18, data.length, true);
      local.setUint32(22, data.length, true);
      local.setUint16(26, nameBytes.length, true);
      const central = new DataView(new ArrayBuffer(46));
      central.setUint32(0, 0x02014b50, true);
      central.setUint16(4, 20, true);
      central.setUint16(6, 20, true);
      central.setUint16(8, 0x0800, true);
      central.setUint16(12, time, true);
      central.setUint16(14, date, true);
      central.setUint32(16, crc, true);
      central.setUint32(20, data.length, true);
      central.setUint32(24, data.length, true);
      central.setUint16(28, nameBytes.length, true);
      central.setUint32(42, offset, true);
      parts.push(new Uint8Array(local.buffer), nameBytes, data);
      directory.push(new Uint8Array(central.buffer), nameBytes);
      offset += 30 + nameBytes.length + data.length;
    }
    const size = directory.reduce((n, p) => n + p.length, 0);
    const end = new DataView(new ArrayBuffer(22));
    end.setUint32(0, 0x06054b50, true);
    end.setUint16(8, files.length, true);
    end.setUint16(10, files.length, true);
    end.setUint32(12, size, true);
    end.setUint32(16, offset, true);
    return new Blob([...parts, ...directory, new Uint8Array(end.buffer)], { type: "application/zip" });
  }

  function npy(descr, shape, data) {
    const dims = shape.length === 1 ? `${shape[0]},` : shape.join(", ");
    let header = `{'descr': '${descr}', 'fortran_order': False, 'shape': (${dims}), }`;
    header += " ".repeat(63 - ((10 + header.length) % 64)) + "\n";
    const head = new Uint8Array(10 + header.length);
    head.set([0x93, 0x4e, 0x55, 0x4d, 0x50, 0x59, 1, 0]);
    new DataView(head.buffer).setUint16(8, header.length, true);
    for (let i = 0; i < header.length; i++) head[10 + i] = header.charCodeAt(i);
    return concat([head, data]);
  }

  function save(blob, name) {
    const link = document.createElement("a");
    link.href = URL.createObjectURL(blob);
    link.download = name;
    document.body.append(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(link.href), 60000);
  }

  function runName(run) {
    if (run.method !== "net") return run.method;
    return `net-${run.quality}${run.binning > 1 ? `-binning${run.binning}` : ""}`;
  }

  async function downloadPngs() {
    const files = [];
    const total = state.runs.reduce((n, r) => n + r.centres.length, 0);
    ui.downloadPng.disabled = true;
    try {
      for (const run of state.runs) {
        for (const centre of run.centres) {
          const png = await encodePng(run.frames.get(centre), run.width, run.height);
          files.push({ name: `${runName(run)}/${String(centre).padStart(6, "0")}.png`, data: png });
          if (files.length % 20 === 0) ui.downloadNote.textContent = `encoding PNG ${files.length} of ${total}…`;
        }
      }
      save(zipFiles(files), `${state.source.stem}_${state.runs.map(runName).join("_vs_")}.zip`);
      ui.downloadNote.textContent = `${files.length} PNGs (gamma ${state.gamma})`;
    } finally {
      updateButtons();
    }
  }

  function downloadNpz() {
    const files = [];
    for (const [i, run] of state.runs.entries()) {
      const suffix = i ? "_b" : "";
      const n = run.centres.length;
      const frames = new Uint8Array(n * run.width * run.height);
      run.centres.forEach((centre, j) => frames.set(run.frames.get(centre), j * run.width * run.height));
      const centres = new BigInt64Array(run.centres.map(BigInt));
      files.push({ name: `frames${suffix}.npy`, data: npy("|u1", [n, run.height, run.width], frames) });
      files.push({ name: `centers${suffix}.npy`, data: npy("<i8", [n], new Uint8Array(centres.buffer)) });
    }
    const gamma = new Float64Array([state.gamma]);
    files.push({ name: "gamma.npy", data: npy("<f8", [], new Uint8Array(gamma.buffer)) });
    save(zipFiles(files), `${state.source.stem}_${state.runs.map(runName).join("_vs_")}.npz`);
    ui.downloadNote.textContent = "frames: uint8 display values (gamma in the file); centers: int64";
  }

  // ---------------------------------------------------------------- wiring

  function updateButtons() {
    const running = state.abort !== null;
    ui.run.disabled = running || state.loading || !state.source;
    ui.stop.disabled = !running;
    const haveFrames = state.runs.some((r) => r.centres.length > 0);
    ui.downloadPng.disabled = running || !haveFrames;
    ui.downloadNpz.disabled = running || !haveFrames;
    ui.quality.disabled = ui.method.value !== "net";
    ui.binning.disabled = ui.binningHint.hidden = !binnable();
    ui.binningNa.hidden = binnable();
    ui.window.disabled = ui.method.value === "net" && ui.compare.value !== "tfp" && ui.compare.value !== "tfi";
    ui.stride.disabled = !ui.useStride.checked;
    ui.centers.disabled = ui.useStride.checked;
  }

  async function checkService() {
    try {
      const models = await fetch("v1/models").then((r) => (r.ok ? r.json() : null));
      const ready = await fetch("readyz");
      const model = models?.models?.[0];
      if (model?.geometry) netFrames = model.geometry.window_frames;
      const name = model ? `model ${model.name}` : "no model yet";
      ui.serviceStatus.textContent = `${name} · ${ready.ok ? "ready" : "not ready: " + (await errorDetail(ready))}`;
      if (!ready.ok) setTimeout(checkService, 2000);
    } catch {
      ui.serviceStatus.textContent = "the service does not answer";
      setTimeout(checkService, 5000);
    }
  }

  ui.form.addEventListener("submit", (event) => {
    event.preventDefault();
    reconstruct();
  });
  ui.stop.addEventListener("click", () => state.abort?.abort());
  ui.file.addEventListener("change", () => {
    if (ui.file.files.length) loadFile(ui.file.files[0]);
  });
  ui.preset.addEventListener("click", () => {
    if (ui.height.disabled) return;
    ui.height.value = 250;
    ui.width.value = 400;
    describeSource();
  });
  for (const input of [ui.height, ui.width]) input.addEventListener("input", describeSource);
  for (const input of [ui.method, ui.quality, ui.compare, ui.useStride, ui.useCenters]) {
    input.addEventListener("change", updateButtons);
  }
  ui.slider.addEventListener("input", () => goTo(Number(ui.slider.value)));
  ui.prev.addEventListener("click", () => goTo(state.index - 1));
  ui.next.addEventListener("click", () => goTo(state.index + 1));
  ui.zoom.addEventListener("change", scheduleDraw);
  ui.layout.addEventListener("change", () => {
    ui.toggle.hidden = ui.layout.value !== "toggle";
    scheduleDraw();
  });
  ui.toggle.addEventListener("click", () => {
    state.showB = !state.showB;
    scheduleDraw();
  });
  ui.downloadPng.addEventListener("click", () => downloadPngs().catch((e) => showError(e.message)));
  ui.downloadNpz.addEventListener("click", () => {
    try {
      downloadNpz();
    } catch (e) {
      showError(e.message);
    }
  });
  window.addEventListener("resize", scheduleDraw);
  document.addEventListener("keydown", (event) => {
    if (event.target instanceof HTMLInputElement && event.target.type !== "range") return;
    if (event.target instanceof HTMLSelectElement || event.target instanceof HTMLTextAreaElement) return;
    if (event.key === "ArrowLeft" && event.target !== ui.slider) goTo(state.index - 1);
    else if (event.key === "ArrowRight" && event.target !== ui.slider) goTo(state.index + 1);
    else if ((event.key === "t" || event.key === "T") && state.runs.length > 1 && ui.layout.value === "toggle") {
      state.showB = !state.showB;
      scheduleDraw();
    }
  });

  updateButtons();
  drawNow();
  checkService();
})();
