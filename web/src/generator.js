// onnxruntime-web wrapper: pose -> (texture, displacement) maps. WebGPU where available, else wasm.
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

async function webgpuAvailable() {
  try {
    return !!(navigator.gpu && (await navigator.gpu.requestAdapter()));
  } catch (e) {
    return false;
  }
}

export class Generator {
  static async create(ort, modelUrl, manifest, preferred = 'auto') {
    const gen = new Generator();
    gen.ort = ort;
    gen.manifest = manifest;
    const wantGpu = preferred === 'webgpu' || (preferred === 'auto' && (await webgpuAvailable()));
    const response = await fetch(modelUrl);
    if (!response.ok) throw new Error(`${modelUrl}: HTTP ${response.status}`);
    const bytes = new Uint8Array(await response.arrayBuffer());
    let lastError = null;
    for (const ep of wantGpu ? ['webgpu', 'wasm'] : ['wasm']) {
      try {
        gen.session = await ort.InferenceSession.create(bytes, { executionProviders: [ep], graphOptimizationLevel: 'all' });
        gen.backend = ep;
        return gen;
      } catch (e) {
        lastError = e;
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
