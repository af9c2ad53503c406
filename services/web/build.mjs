// Builds the viewer and the ops page into dist/ (committed: serving needs no npm at run time).
// Assets get content hashes in their names, so the API can cache them forever; the two HTML pages
// (index.html, ops.html) are rewritten with those names and served with no-cache.
import { build } from 'esbuild';
import { createHash } from 'node:crypto';
import { copyFileSync, mkdirSync, readFileSync, rmSync, writeFileSync } from 'node:fs';
import { basename, dirname, join } from 'node:path';
import { createRequire } from 'node:module';
import { fileURLToPath } from 'node:url';

const here = dirname(fileURLToPath(import.meta.url));
const src = join(here, 'src');
const dist = join(here, 'dist');
rmSync(dist, { recursive: true, force: true });
mkdirSync(dist);

// MapLibre runs its tile parsing in a module worker loaded from its own file.
const require = createRequire(import.meta.url);
const workerSrc = join(dirname(require.resolve('maplibre-gl/package.json')), 'dist', 'maplibre-gl-worker.mjs');
const workerHash = createHash('sha256').update(readFileSync(workerSrc)).digest('hex').slice(0, 8);
const workerFile = `maplibre-gl-worker-${workerHash}.mjs`;
copyFileSync(workerSrc, join(dist, workerFile));

const result = await build({
  entryPoints: { viewer: join(src, 'viewer.js'), ops: join(src, 'ops.js') },
  outdir: dist,
  entryNames: '[name]-[hash]',
  assetNames: '[name]-[hash]',
  bundle: true,
  format: 'esm',
  splitting: false,
  minify: true,
  target: ['chrome110', 'firefox115', 'safari16'],
  define: { __WORKER_FILE__: JSON.stringify(workerFile) },
  legalComments: 'eof',
  metafile: true,
  logLevel: 'warning',
});

// entry name -> the emitted file names (js, and the css bundle of its imported stylesheets)
const emitted = {};
for (const [out, meta] of Object.entries(result.metafile.outputs)) {
  if (!meta.entryPoint) continue;
  const entry = basename(meta.entryPoint, '.js');
  emitted[entry] = { js: basename(out), css: meta.cssBundle ? basename(meta.cssBundle) : '' };
}

for (const [page, entry] of [['index.html', 'viewer'], ['ops.html', 'ops']]) {
  const html = readFileSync(join(src, entry + '.html'), 'utf8')
    .replace('{{js}}', emitted[entry].js)
    .replace('{{css}}', emitted[entry].css);
  writeFileSync(join(dist, page), html);
}
console.log('built', JSON.stringify({ ...emitted, worker: workerFile }));
