// onnxruntime-web wrapper: pose -> (texture, displacement) maps. WebGPU where the browser gives an
// adapter (fp16 weights where it takes them), else wasm; the page says which and why.
import { poseToModelInput } from './pose.js';

export async function loadOrt() {
  const ort = await import(/* external */ './ort/ort.min.mjs');
  ort.env.wasm.wasmPaths = new URL('./ort/', import.meta.url).href;
  ort.env.wasm.numThreads = self.crossOriginIsolated ? Math.min(4, navigator.hardwareConcurrency || 1) : 1;
  // Inference runs on the page's thread by default: measured in Chromium (2 cores), the proxy worker
  // made a 128² generator 6x slower (132 ms vs 22 ms). `?proxy=1` moves it to a worker, which keeps
  // the render loop drawing during long inferences at that cost.
  ort.env.wasm.proxy = new URLSearchParams(location.search).get('proxy') === '1';
  return ort;
}

/** The WebGPU adapter, or a sentence saying why there is none (no navigator.gpu: not Chromium with
 * WebGPU, or not a secure context; requestAdapter gave null: no usable GPU, nor SwiftShader). */
async function webgpuAdapter(timeoutMs = self.UVATAR_ADAPTER_TIMEOUT_MS || ADAPTER_TIMEOUT_MS) {
  if (!navigator.gpu) return { adapter: null, why: 'no WebGPU in this browser' };
  try {
    const adapter = await withTimeout(navigator.gpu.requestAdapter(), timeoutMs, 'WebGPU adapter request');
    return adapter ? { adapter, why: null } : { adapter: null, why: 'no WebGPU adapter' };
  } catch (e) {
    return { adapter: null, why: `WebGPU adapter request failed: ${e.message || e}` };
  }
}

/** A browser's GPU process can stall (a busy or lost device, a software adapter under load): the
 * adapter request and a WebGPU session get this long before the viewer falls back to wasm and says so
 * (a page may set window.UVATAR_ADAPTER_TIMEOUT_MS first, as the tests do). */
const ADAPTER_TIMEOUT_MS = 20000;
const WEBGPU_SESSION_TIMEOUT_MS = 60000;

/** `promise`, or a rejection naming `what` after `ms` milliseconds. */
function withTimeout(promise, ms, what) {
  let timer;
  const expired = new Promise((_, reject) => { timer = setTimeout(() => reject(new Error(`${what} timed out after ${ms / 1000} s`)), ms); });
  return Promise.race([promise, expired]).finally(() => clearTimeout(timer));
}

async function fetchBytes(url) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return new Uint8Array(await response.arrayBuffer());
}

export class Generator {
  /** preferred: 'auto' (WebGPU when an adapter exists, else wasm), 'webgpu' or 'wasm'. precision:
   * 'auto' (the fp16 graph, manifest generator.file_fp16, on WebGPU when the adapter has shader-f16),
   * 'fp16' or 'fp32'. Sets backend ('webgpu' | 'wasm'), precision ('fp16' | 'fp32'), adapter
   * ('vendor architecture' of the WebGPU adapter) and note (why not WebGPU / not fp16, or ''). */
  static async create(ort, avatarUrl, manifest, preferred = 'auto', precision = 'auto') {
    const gen = new Generator();
    gen.ort = ort;
    gen.manifest = manifest;
    const notes = [];
    const { adapter, why } = preferred === 'wasm' ? { adapter: null, why: 'wasm asked for (?ep=wasm)' } : await webgpuAdapter();
    if (!adapter && why) notes.push(why);
    const info = adapter && (adapter.info || {});
    gen.adapter = info ? `${info.vendor || ''} ${info.architecture || ''}`.trim() || 'unknown' : null;
    const fp16File = manifest.generator.file_fp16;
    const fp16Ok = !!(adapter && adapter.features && adapter.features.has('shader-f16'));
    const tries = [];
    // fp16 on WebGPU only with shader-f16: on SwiftShader (none) onnxruntime-web 1.23 still takes the
    // fp16 graph and returns wrong maps (texture off by 0.8, tests/test_viewer_webgpu.py)
    if (adapter) {
      if (fp16File && precision !== 'fp32' && fp16Ok) tries.push(['webgpu', 'fp16']);
      else if (fp16File && precision === 'auto') notes.push('adapter without shader-f16: fp32 weights');
      else if (fp16File && precision === 'fp16') notes.push('adapter without shader-f16: fp16 on wasm');
      if (precision !== 'fp16') tries.push(['webgpu', 'fp32']);
    }
    tries.push(['wasm', precision === 'fp16' && fp16File ? 'fp16' : 'fp32']);
    const bytes = {};
    let lastError = null;
    for (const [ep, prec] of tries) {
      const file = prec === 'fp16' ? fp16File : manifest.generator.file;
      try {
        bytes[file] = bytes[file] || (await fetchBytes(avatarUrl + file));
        const created = ort.InferenceSession.create(bytes[file], { executionProviders: [ep], graphOptimizationLevel: 'all' });
        gen.session = ep === 'webgpu' ? await withTimeout(created, WEBGPU_SESSION_TIMEOUT_MS, 'WebGPU session') : await created;
        gen.backend = ep;
        gen.precision = prec;
        gen.note = notes.join('; ');
        return gen;
      } catch (e) {
        lastError = e;
        notes.push(`${ep} ${prec} failed: ${String(e.message || e).split('\n')[0].slice(0, 120)}`);
      }
    }
    throw lastError;
  }

  /** pose (J*3 numbers) -> {texture: Float32Array(3*R*R), displacement: Float32Array(3*R*R), ms}.
   * Calls are serialized (an onnxruntime session runs one inference at a time). */
  run(pose) {
    const next = (this._queue || Promise.resolve()).then(() => this._run(pose));
    this._queue = next.catch(() => {});
    return next;
  }

  async _run(pose) {
    const g = this.manifest.generator;
    const input = poseToModelInput(pose, this.manifest.pose_encoding);
    const t0 = performance.now();
    const feeds = { [g.input]: new this.ort.Tensor('float32', input, [1, input.length]) };
    const out = await this.session.run(feeds);
    const texture = await out[g.texture_output].getData();
    const displacement = await out[g.displacement_output].getData();
    const ms = performance.now() - t0;
    return { texture, displacement, ms, dims: out[g.texture_output].dims };
  }
}
