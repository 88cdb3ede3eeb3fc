// How GLB answers look in three.js (its GLTFLoader, in headless chromium), each as written and
// again without its material (what a viewer shows with glTF's default, fully metallic and
// front sides only): 4 views around each file; prints per file and in all the share of the
// frame the mesh covers and the share of those pixels that are near black (luminance < 50).
// Usage: node scripts/glb-in-three.mjs ANSWER.glb ...   (needs `cd web && npm ci` and
// chromium; BROWSER=/path/to/chromium to pick another)
import http from 'node:http';
import fs from 'node:fs';
import path from 'node:path';
import { createRequire } from 'node:module';
import { fileURLToPath } from 'node:url';

const web = path.join(path.dirname(fileURLToPath(import.meta.url)), '..', 'web');
const modules = path.join(web, 'node_modules');
const puppeteer = createRequire(path.join(web, 'package.json'))('puppeteer-core');
const files = process.argv.slice(2);
if (files.length === 0) {
  console.error('usage: node scripts/glb-in-three.mjs ANSWER.glb ...');
  process.exit(2);
}

/** The GLB `bytes` without materials: its JSON chunk rewritten, the binary chunk as it was. */
function withoutMaterial(bytes) {
  const jsonLength = bytes.readUInt32LE(12);
  const json = JSON.parse(bytes.subarray(20, 20 + jsonLength).toString());
  delete json.materials;
  for (const mesh of json.meshes ?? []) for (const p of mesh.primitives) delete p.material;
  let text = JSON.stringify(json);
  text += ' '.repeat((4 - (text.length % 4)) % 4);
  const rest = bytes.subarray(20 + jsonLength);
  const header = Buffer.alloc(20);
  header.write('glTF', 0);
  header.writeUInt32LE(2, 4);
  header.writeUInt32LE(20 + text.length + rest.length, 8);
  header.writeUInt32LE(text.length, 12);
  header.write('JSON', 16);
  return Buffer.concat([header, Buffer.from(text), rest]);
}

const page = `<!doctype html><body style="margin:0">
<script type="importmap">{"imports":{"three":"/three/build/three.module.js",
"three/addons/":"/three/examples/jsm/"}}</script>
<script type="module">
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
window.render = (url, azimuth) => new Promise((resolve, reject) => {
  const renderer = new THREE.WebGLRenderer({ preserveDrawingBuffer: true });
  renderer.setSize(256, 256);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xffffff);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 1.5));
  const sun = new THREE.DirectionalLight(0xffffff, 2.5);
  sun.position.set(1, 2, 3);
  scene.add(sun);
  new GLTFLoader().load(url, (gltf) => {
    scene.add(gltf.scene);
    const box = new THREE.Box3().setFromObject(gltf.scene);
    const c = box.getCenter(new THREE.Vector3());
    const r = box.getSize(new THREE.Vector3()).length();
    const camera = new THREE.PerspectiveCamera(40, 1, r / 100, r * 10);
    const [x, z] = [Math.sin(azimuth), Math.cos(azimuth)];
    camera.position.set(c.x + 1.4 * r * x, c.y + 0.5 * r, c.z + 1.4 * r * z);
    camera.lookAt(c);
    renderer.render(scene, camera);
    const gl = renderer.getContext();
    const px = new Uint8Array(256 * 256 * 4);
    gl.readPixels(0, 0, 256, 256, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let covered = 0, dark = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (765 - px[i] - px[i + 1] - px[i + 2] > 6) {
        covered += 1;
        if ((px[i] + px[i + 1] + px[i + 2]) / 3 < 50) dark += 1;
      }
    }
    renderer.dispose();
    resolve({ covered, dark, pixels: 256 * 256 });
  }, undefined, (e) => reject(String(e)));
});
document.title = 'ready';
</script>`;

const pct = (x) => `${(100 * x).toFixed(1)}%`;

const served = new Map();
files.forEach((f, i) => {
  const bytes = fs.readFileSync(f);
  served.set(`/as-written/${i}.glb`, bytes);
  served.set(`/no-material/${i}.glb`, withoutMaterial(bytes));
});
const server = http.createServer((req, res) => {
  const url = req.url.split('?')[0];
  if (url === '/') return res.end(page);
  if (served.has(url)) return res.end(served.get(url));
  const file = path.join(modules, url);
  if (!file.startsWith(modules + path.sep)) return res.writeHead(404).end();
  fs.readFile(file, (err, data) => {
    if (err) return res.writeHead(404).end();
    const type = file.endsWith('.js') ? 'text/javascript' : 'application/octet-stream';
    res.writeHead(200, { 'content-type': type });
    res.end(data);
  });
});
await new Promise((resolve) => server.listen(0, '127.0.0.1', resolve));
const browser = await puppeteer.launch({
  executablePath: process.env.BROWSER || '/usr/bin/chromium',
  args: ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
});
try {
  const tab = await browser.newPage();
  await tab.goto(`http://127.0.0.1:${server.address().port}/`);
  await tab.waitForFunction(() => document.title === 'ready');
  // Covered pixels, near-black ones and all pixels, over every view of every file.
  const totals = { 'as-written': [0, 0, 0], 'no-material': [0, 0, 0] };
  console.log('| file | covered, as written | no material | near black, as written | no material |');
  console.log('|---|---|---|---|---|');
  for (const [i, f] of files.entries()) {
    const row = {};
    for (const kind of Object.keys(totals)) {
      let covered = 0, dark = 0, pixels = 0;
      for (let k = 0; k < 4; k++) {
        const azimuth = 0.6 + (k * Math.PI) / 2;
        const s = await tab.evaluate((u, a) => window.render(u, a), `/${kind}/${i}.glb`, azimuth);
        covered += s.covered;
        dark += s.dark;
        pixels += s.pixels;
      }
      row[kind] = [covered / pixels, dark / Math.max(covered, 1)];
      totals[kind] = [totals[kind][0] + covered, totals[kind][1] + dark, totals[kind][2] + pixels];
    }
    const [a, b] = [row['as-written'], row['no-material']];
    console.log(`| ${path.basename(f)} | ${pct(a[0])} | ${pct(b[0])} | ${pct(a[1])} | ${pct(b[1])} |`);
  }
  const [a, b] = [totals['as-written'], totals['no-material']];
  console.log(
    `all ${files.length}: covered ${pct(a[0] / a[2])} as written against ${pct(b[0] / b[2])}` +
      ` without the material; near black ${pct(a[1] / a[0])} of the covered pixels against` +
      ` ${pct(b[1] / b[0])}`,
  );
} finally {
  await browser.close();
  server.close();
}
