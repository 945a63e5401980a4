// Builds the page into python/caviar/view/static/: view.js (three.js and the page,
// bundled and minified by esbuild), index.html, style.css and the bundled packages' licences.
import { build } from 'esbuild';
import { copyFileSync, mkdirSync, readFileSync, writeFileSync } from 'node:fs';

const out = new URL('../python/caviar/view/static/', import.meta.url);
mkdirSync(out, { recursive: true });
await build({
  entryPoints: [new URL('src/main.js', import.meta.url).pathname],
  bundle: true, minify: true, format: 'iife', target: 'es2020',
  legalComments: 'none', outfile: new URL('view.js', out).pathname, logLevel: 'info',
});
for (const f of ['index.html', 'style.css']) copyFileSync(new URL(`src/${f}`, import.meta.url), new URL(f, out));
const three = JSON.parse(readFileSync(new URL('node_modules/three/package.json', import.meta.url)));
writeFileSync(new URL('THIRD-PARTY.txt', out),
  `view.js bundles three.js ${three.version} (https://threejs.org), MIT licence:\n\n` +
  readFileSync(new URL('node_modules/three/LICENSE', import.meta.url), 'utf8'));
