// Build the viewer into ../src/uvatar/viewer/static (committed, so a Python install needs no npm).
// Usage: cd web && npm ci && npm run build   ($UVATAR_VIEWER_OUT: build elsewhere, e.g. for a test)
// Writes static/build.json: the SHA-256 of the sources it was built from (SOURCES, see sourcesDigest)
// and of every file it wrote; tests/test_viewer_assets.py checks both against the tree.
import { build } from 'esbuild';
import { createHash } from 'node:crypto';
import { copyFileSync, mkdirSync, readdirSync, readFileSync, rmSync, writeFileSync } from 'node:fs';
import { join, relative, resolve } from 'node:path';

const out = process.env.UVATAR_VIEWER_OUT
  ? resolve(process.env.UVATAR_VIEWER_OUT) + '/'
  : new URL('../src/uvatar/viewer/static/', import.meta.url).pathname;
const sha256 = (bytes) => createHash('sha256').update(bytes).digest('hex');
const walk = (dir) => readdirSync(dir, { withFileTypes: true }).flatMap(
  (e) => (e.isDirectory() ? walk(join(dir, e.name)) : [join(dir, e.name)]));
const byCodepoint = (a, b) => (a < b ? -1 : a > b ? 1 : 0);
// the build's inputs, relative to web/: one line "path sha256" each, sorted, hashed together
const SOURCES = ['build.mjs', 'package.json', 'package-lock.json', 'index.html', 'viewer.css'];
function sourcesDigest() {
  const files = [...SOURCES, ...walk('src')].sort(byCodepoint);
  return sha256(files.map((f) => `${f} ${sha256(readFileSync(f))}\n`).join(''));
}
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
const files = Object.fromEntries(walk(out).map((f) => [relative(out, f), sha256(readFileSync(f))])
  .sort((a, b) => byCodepoint(a[0], b[0])));
writeFileSync(out + 'build.json', JSON.stringify({ sources_sha256: sourcesDigest(), files }, null, 2) + '\n');
console.log(`built ${out}`);
