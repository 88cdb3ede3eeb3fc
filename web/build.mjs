// Bundles src/main.js and three.js, minified by esbuild, into dist/app.js, which the binary
// embeds (with src/index.html and src/style.css as they are), and copies three.js's Draco
// decoder for glTF (a wrapper and its WebAssembly, which the page loads only for a
// Draco-compressed file) into dist/draco/. `--check` builds in memory and fails when dist/
// differs, so that the committed files are what the locked packages make.

import { readFile, writeFile, mkdir } from 'node:fs/promises';
import { build } from 'esbuild';

const here = new URL('.', import.meta.url);
const check = process.argv.includes('--check');

const bundle = await build({
  entryPoints: [new URL('src/main.js', here).pathname],
  bundle: true,
  format: 'esm',
  minify: true,
  target: 'es2022',
  legalComments: 'eof',
  write: false,
});
const draco = new URL('node_modules/three/examples/jsm/libs/draco/gltf/', here);
const outputs = { 'app.js': bundle.outputFiles[0].contents };
for (const name of ['draco_wasm_wrapper.js', 'draco_decoder.wasm']) {
  outputs[`draco/${name}`] = await readFile(new URL(name, draco));
}

let stale = [];
for (const [name, contents] of Object.entries(outputs)) {
  const path = new URL(`dist/${name}`, here);
  if (check) {
    const committed = await readFile(path).catch(() => Buffer.alloc(0));
    if (!Buffer.from(contents).equals(committed)) stale.push(name);
  } else {
    await mkdir(new URL('dist/draco/', here), { recursive: true });
    await writeFile(path, contents);
    console.log(`dist/${name}: ${contents.length} bytes`);
  }
}
if (stale.length) {
  console.error(`web/dist is not what \`npm run build\` makes: ${stale.join(', ')} differ`);
  process.exit(1);
}
