// Build the viewer into ../src/uvatar/viewer/static (committed, so a Python install needs no npm).
// Usage: cd web && npm ci && npm run build
import { build } from 'esbuild';
import { copyFileSync, mkdirSync, rmSync } from 'node:fs';

const out = new URL('../src/uvatar/viewer/static/', import.meta.url).pathname;
rmSync(out, { recursive: true, force: true });
mkdirSync(out + 'ort', { recursive: true });

await build({
  entryPoints: ['src/main.js'],
  bundle: true,
  format: 'esm',
  minify: true,
  target: 'es2020',
  outfile: out + 'viewer.js',
  external: ['./ort/*'],
  legalComments: 'linked',
  logLevel: 'info',
});

// onnxruntime-web: the default build (wasm CPU backend + WebGPU through JSEP, one .wasm), loaded at
// run time from static/ort/. The other wasm variants (plain, asyncify) are not shipped.
const ortDist = 'node_modules/onnxruntime-web/dist/';
for (const f of ['ort.min.mjs', 'ort-wasm-simd-threaded.jsep.mjs', 'ort-wasm-simd-threaded.jsep.wasm']) {
  copyFileSync(ortDist + f, out + 'ort/' + f);
}
for (const f of ['index.html', 'viewer.css']) copyFileSync(f, out + f);
console.log(`built ${out}`);
