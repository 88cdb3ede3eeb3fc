// The viewer in a real browser against a running `meshstream serve`: Debian's chromium (over
// CDP) or Firefox ESR (over WebDriver BiDi), both driven by puppeteer-core. Run by
// tests/web_viewer.rs, which starts the server; by hand:
//   MESHSTREAM_URL=http://127.0.0.1:8080 ARTIFACTS=/tmp/viewer node web/tests/viewer.spec.mjs
//   BROWSER=firefox ... xvfb-run -a node web/tests/viewer.spec.mjs
// It writes screenshots, the downloaded files and result.json (what it saw) to ARTIFACTS.

import assert from 'node:assert/strict';
import { copyFile, mkdir, readFile, readdir, rm, writeFile } from 'node:fs/promises';
import { statSync } from 'node:fs';
import puppeteer from 'puppeteer-core';

const base = process.env.MESHSTREAM_URL;
const artifacts = process.env.ARTIFACTS;
const browserName = process.env.BROWSER || 'chromium';
assert(base && artifacts, 'set MESHSTREAM_URL and ARTIFACTS');
await mkdir(artifacts, { recursive: true });
const downloads = `${artifacts}/downloads`;
await rm(downloads, { recursive: true, force: true });
await mkdir(downloads);
const examples = new URL('../examples/', import.meta.url);
const step = (text) => console.log(`viewer (${browserName}): ${text}`);

const launches = {
  chromium: {
    browser: 'chrome',
    executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: [
      '--no-sandbox',
      '--disable-gpu',
      // WebGL without a GPU: ANGLE on SwiftShader, which chromium no longer falls back to alone.
      '--use-angle=swiftshader',
      '--enable-unsafe-swiftshader',
      '--disable-quic',
      '--no-first-run',
      '--disable-background-networking',
      '--disable-component-update',
      '--disable-sync',
    ],
  },
  // Headless Firefox has no WebGL without a display on Linux: tests/web_viewer.rs runs it on a
  // virtual one (xvfb-run), where it draws with Mesa's llvmpipe.
  firefox: {
    browser: 'firefox',
    executablePath: process.env.FIREFOX || '/usr/bin/firefox-esr',
    headless: false,
  },
};
assert(launches[browserName], `BROWSER is chromium or firefox, not ${browserName}`);
// puppeteer gives every launch a fresh, empty profile.
const browser = await puppeteer.launch({ ...launches[browserName], defaultViewport: { width: 1000, height: 620 } });
const result = {};
try {
  const context = await browser.createBrowserContext({ downloadBehavior: { policy: 'allow', downloadPath: downloads } });
  const page = await context.newPage();
  const pageErrors = [];
  page.on('pageerror', (error) => pageErrors.push(error.message));
  page.on('console', (message) => {
    // Chromium logs every refused request (the 400 below is one) as an error: not the page's.
    if (message.type() === 'error' && !message.text().startsWith('Failed to load resource')) {
      pageErrors.push(message.text());
    }
  });
  // CI runs this beside the other tests on a few cores: be patient.
  page.setDefaultTimeout(120_000);
  const shoot = (name) => page.screenshot({ path: `${artifacts}/${name}.png` });
  const text = (selector) => page.$eval(selector, (e) => e.textContent);
  const attribute = (selector, name) => page.$eval(selector, (e, name) => e.getAttribute(name), name);
  const fill = (selector, value) => page.locator(selector).fill(value);
  const state = () => attribute('body', 'data-state');
  const faceCount = async () => Number(await text('#face-count'));
  // What the canvas shows: the share of its pixels off the background, and their extent.
  const drawn = () => page.evaluate(() => {
    const canvas = document.getElementById('canvas');
    const copy = Object.assign(document.createElement('canvas'), { width: canvas.width, height: canvas.height });
    const context = copy.getContext('2d');
    context.drawImage(canvas, 0, 0);
    const { data } = context.getImageData(0, 0, copy.width, copy.height);
    const background = [0x20, 0x24, 0x2b];
    let differing = 0;
    const box = { left: Infinity, right: -Infinity, top: Infinity, bottom: -Infinity };
    for (let i = 0; i < data.length; i += 4) {
      const d = Math.abs(data[i] - background[0]) + Math.abs(data[i + 1] - background[1])
        + Math.abs(data[i + 2] - background[2]);
      if (d > 30) {
        differing++;
        const [x, y] = [(i / 4) % copy.width, Math.floor(i / 4 / copy.width)];
        Object.assign(box, {
          left: Math.min(box.left, x), right: Math.max(box.right, x),
          top: Math.min(box.top, y), bottom: Math.max(box.bottom, y),
        });
      }
    }
    return {
      fraction: differing / (data.length / 4),
      width: Math.max(0, box.right - box.left),
      height: Math.max(0, box.bottom - box.top),
    };
  });
  const running = async () => {
    const text = await (await fetch(`${base}/metrics`)).text();
    const line = text.split('\n').find((l) => l.startsWith('meshstream_running_sequences '));
    assert(line, `no running_sequences gauge in /metrics:\n${text}`);
    return Number(line.split(' ')[1]);
  };

  step('open the page');
  await page.goto(base);
  await page.waitForFunction(() => !document.getElementById('server').textContent.startsWith('Asking'));
  const serverLine = await text('#server');
  assert.match(serverLine, /up to \d+ faces/, serverLine);
  const info = JSON.parse(await (await fetch(`${base}/v1/info`)).text());
  assert.equal(await attribute('#max_faces', 'placeholder'), String(info.limits.max_faces));
  assert.equal(await attribute('#candidates', 'placeholder'), String(info.defaults.candidates.whole_mesh));

  step('upload a point cloud and watch its faces arrive');
  await fill('#max_faces', '400');
  const streamed = page.waitForResponse((r) => r.url().includes('/reconstruct'));
  const fileInput = await page.$('#file');
  await fileInput.uploadFile(new URL('mug-points.ply', examples).pathname);
  await page.waitForFunction(() => document.getElementById('input-name').textContent.endsWith('2048 points'));
  assert.equal((await streamed).headers()['content-type'], 'application/x-ndjson');
  // The server's whole-mesh answer, with the first candidate's faces as drafts meanwhile.
  const asked = new URL((await streamed).url()).searchParams;
  for (const name of ['candidates', 'weld_radius', 'fit_rounds']) {
    assert.equal(asked.get(name), String(info.defaults[name].whole_mesh), `${name} in ${asked}`);
  }
  assert.equal(asked.get('drafts'), 'true');
  // A screenshot while the faces stream in (if the stream outruns the poll, at its end).
  await page.waitForFunction(() => Number(document.getElementById('face-count').textContent) >= 60
    || document.body.dataset.state !== 'running');
  await shoot('streaming');
  // Still running after the shot: the shot shows faces streaming in, not the end.
  result.streaming_state = await state();
  result.streaming_faces = await faceCount();
  await page.waitForFunction(() => document.body.dataset.state !== 'running');
  assert.equal(await state(), 'done', await text('#error'));
  // The page's done line, and the same request sent here: decoding is seeded, so it streams the
  // same faces (the page's own response body is gone: the page read it as a stream).
  const pageDone = (await text('#progress')).match(/Done: (\d+) faces/);
  assert(pageDone, 'no done line on the page');
  const direct = await fetch(`${base}/reconstruct?${asked}`, {
    method: 'POST',
    headers: { 'content-type': 'application/ply', accept: 'application/x-ndjson' },
    body: await readFile(new URL('mug-points.ply', examples)),
  });
  const lines = (await direct.text()).trim().split('\n').map((l) => JSON.parse(l));
  const done = lines.at(-1);
  assert.equal(done.type, 'done');
  assert.equal(lines.filter((l) => l.type === 'face').length, done.faces);
  result.draft_faces = lines.filter((l) => l.type === 'draft').length;
  assert(result.draft_faces > 0, 'no drafts before the answer');
  result.done_faces = done.faces;
  result.page_faces = await faceCount();
  assert.equal(result.page_faces, done.faces, 'the page counts the faces the done event reports');
  assert.equal(Number(pageDone[1]), done.faces);
  // What the answer says of itself, as the done event gives it.
  const q = done.quality;
  assert(q && q.edges > 0 && q.input_chamfer > 0, JSON.stringify(done));
  const build = q.watertight ? 'watertight' : `${q.boundary_edges} of ${q.edges} edges open`;
  assert.match(await text('#progress'), new RegExp(`The mesh: ${q.parts} parts?, ${build}`));
  result.quality = q;
  assert.match(await text('#progress'), /faces\/s · first face after/);
  await shoot('done');

  step('the canvas shows the faces');
  result.lit_fraction = (await drawn()).fraction;
  assert(result.lit_fraction > 0.01, `the canvas is blank: ${result.lit_fraction} of its pixels differ`);
  await page.click('#wireframe');
  assert(await page.$eval('#wireframe', (e) => e.checked));
  await shoot('wireframe');
  await page.click('#wireframe');

  step('download the result as GLB, OBJ, PLY and STL');
  for (const format of ['glb', 'obj', 'ply', 'stl']) {
    await page.click(`[data-format=${format}]`);
    // The browser saves it under the name the page suggests; until it is whole, under another
    // (chromium's .crdownload, Firefox's .part).
    const name = `mug-points-meshstream.${format}`;
    const t0 = Date.now();
    while (!(await readdir(downloads)).includes(name)
      || (await readdir(downloads)).some((f) => f.endsWith('.crdownload') || f.endsWith('.part'))) {
      assert(Date.now() - t0 < 30_000, `no ${name} in ${downloads}: ${await readdir(downloads)}`);
      await new Promise((r) => setTimeout(r, 50));
    }
    await copyFile(`${downloads}/${name}`, `${artifacts}/result.${format}`);
  }
  const glb = await readFile(`${artifacts}/result.glb`);
  assert.equal(glb.toString('latin1', 0, 4), 'glTF');
  assert.equal(glb.readUInt32LE(4), 2);
  assert.equal(glb.readUInt32LE(8), glb.length);

  step('drop a mesh on the page');
  const mesh = (await readFile(new URL('pine-tree.ply', examples))).toString('base64');
  await fill('#max_faces', '150');
  await page.evaluate((base64) => {
    const bytes = Uint8Array.from(atob(base64), (c) => c.charCodeAt(0));
    const transfer = new DataTransfer();
    transfer.items.add(new File([bytes], 'dropped-tree.ply'));
    document.getElementById('drop').dispatchEvent(new DragEvent('drop', { dataTransfer: transfer, bubbles: true }));
  }, mesh);
  // The input line gets its points once the page has read the file, just before it sends it.
  await page.waitForFunction(() => document.body.dataset.state !== 'running'
    && document.getElementById('input-name').textContent.startsWith('dropped-tree.ply (2.0 KB): 4096 points drawn on its surface'));
  assert.equal(await state(), 'done', await text('#error'));
  result.dropped_mesh_faces = await faceCount();
  assert(result.dropped_mesh_faces > 0);
  await shoot('dropped-mesh');

  step('a GLB made small for the web (meshopt, Draco) previews and reconstructs, with z up');
  const webGltf = new URL('../../tests/data/web-gltf/', import.meta.url);
  await page.select('#up', 'z');
  const preview = ': 4096 points drawn on its surface';
  for (const name of ['pine-tree-meshopt.glb', 'pine-tree-draco.glb']) {
    // Sent once the page has tried to read it, and the request sets the page running first.
    const answered = page.waitForResponse((r) => r.url().includes('/reconstruct'));
    await fileInput.uploadFile(new URL(name, webGltf).pathname);
    assert.match((await answered).url(), /[?&]up=z(&|$)/);
    await page.waitForFunction(() => document.body.dataset.state !== 'running');
    assert.equal(await state(), 'done', `${name}: ${await text('#error')}`);
    assert.equal(await text('#input-name'), `${name} (${(statSync(new URL(name, webGltf)).size / 1024).toFixed(1)} KB)${preview}`);
    result[`${name}_faces`] = await faceCount();
    assert(result[`${name}_faces`] > 0, `${name}: no faces`);
  }
  await shoot('web-gltf');
  await page.select('#up', '');
  // The pine tree example knows its source puts z up.
  const example = page.waitForResponse((r) => r.url().includes('/reconstruct'));
  await page.click('[data-example="pine-tree.ply"]');
  assert.match((await example).url(), /[?&]up=z(&|$)/);
  await page.waitForFunction(() => document.body.dataset.state !== 'running');
  assert.equal(await state(), 'done', await text('#error'));
  assert.equal(await page.$eval('#up', (e) => e.value), 'z');
  // Shown standing: the tree (its points with the faces) is taller than wide on the canvas.
  const tree = await drawn();
  assert(tree.height > 1.5 * tree.width, `the tree does not stand: ${JSON.stringify(tree)}`);
  await shoot('pine-tree-example');
  await page.select('#up', '');

  step('an option past the server\'s limit shows the API\'s message');
  const tooMany = await fetch(`${base}/reconstruct?max_faces=999999`, {
    method: 'POST',
    headers: { 'content-type': 'application/ply' },
    body: await readFile(new URL('pine-tree.ply', examples)),
  });
  assert.equal(tooMany.status, 422);
  const { error: limitError } = await tooMany.json();
  await fill('#max_faces', '999999');
  await page.click('#run');
  await page.waitForFunction(() => document.body.dataset.state === 'error');
  result.limit_error_text = await text('#error');
  assert.equal(result.limit_error_text, `422 ${limitError.code}: ${limitError.message}`);

  step('an invalid file shows the API\'s message');
  const broken = Buffer.from('ply\nformat nonsense\nend_header\n');
  const refused = await fetch(`${base}/reconstruct`, {
    method: 'POST',
    headers: { 'content-type': 'application/ply' },
    body: broken,
  });
  const { error } = await refused.json();
  assert.equal(refused.status, 400);
  await writeFile(`${artifacts}/broken.ply`, broken);
  await fileInput.uploadFile(`${artifacts}/broken.ply`);
  // The page is still in the last step's error while it reads the file: wait for this one's.
  await page.waitForFunction((previous) => document.body.dataset.state === 'error'
    && document.getElementById('input-name').textContent.startsWith('broken.ply')
    && document.getElementById('error').textContent !== previous, {}, result.limit_error_text);
  result.error_text = await text('#error');
  assert.equal(result.error_text, `400 ${error.code}: ${error.message}`);
  await shoot('error');

  step('a stream with no faces says so');
  // Three points: the shipped model ends the mesh before its first face.
  await fill('#max_faces', '');
  const header = 'ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n';
  await writeFile(`${artifacts}/three-points.ply`, `${header}0 0 0\n1 0 0\n0 1 0\n`);
  await fileInput.uploadFile(`${artifacts}/three-points.ply`);
  // The page is still in the last step's error while it reads the file: wait for this one's.
  await page.waitForFunction((previous) => document.body.dataset.state === 'error'
    && document.getElementById('input-name').textContent.startsWith('three-points.ply')
    && document.getElementById('error').textContent !== previous, {}, result.error_text);
  result.no_faces_text = await text('#error');
  assert.match(result.no_faces_text, /^The model produced no faces for this input/);

  step('a blank picture says there is no object');
  // A white PNG drawn by the browser: framed as an object (the default), nothing is on it.
  const blank = await page.evaluate(() => {
    const canvas = document.createElement('canvas');
    [canvas.width, canvas.height] = [60, 40];
    const context = canvas.getContext('2d');
    context.fillStyle = '#ffffff';
    context.fillRect(0, 0, 60, 40);
    return canvas.toDataURL('image/png').split(',')[1];
  });
  await writeFile(`${artifacts}/blank.png`, Buffer.from(blank, 'base64'));
  await fileInput.uploadFile(`${artifacts}/blank.png`);
  await page.waitForFunction(() => document.body.dataset.state === 'error'
    && document.getElementById('input-name').textContent.startsWith('blank.png'));
  result.no_object_text = await text('#error');
  assert.match(result.no_object_text, /^422 no_object: no object found in the picture: .*centre_crop/);

  step('an image: diffusion progress, then faces');
  const { image_model: imageModel } = await (await fetch(`${base}/v1/info`)).json();
  assert.equal(await text('#framing-default'), `the server's (${imageModel.default_framing})`);
  await page.select('#framing', 'centre_crop');
  await fill('#steps', '8');
  await fill('#max_faces', '200');
  const generated = page.waitForResponse((r) => r.url().includes('/generate'));
  await page.click('[data-example="chest.png"]');
  assert.equal(new URL((await generated).url()).searchParams.get('framing'), 'centre_crop');
  await page.waitForFunction(() => document.body.dataset.state !== 'running'
    && document.getElementById('input-name').textContent.startsWith('chest'));
  assert.equal(await state(), 'done', await text('#error'));
  result.image_progress = await text('#progress');
  assert.match(result.image_progress, /diffusion step 8 of 8/);
  await shoot('image');

  // Cancelled in the diffusion stage, which is long on a CPU at the most steps the server
  // allows (a point cloud's faces can all arrive before a click lands).
  step('cancel frees the server\'s slot');
  assert.equal(await running(), 0);
  await fill('#steps', await attribute('#steps', 'max'));
  await page.click('#run');
  await page.waitForFunction(() => Number(document.getElementById('progress').textContent.match(/diffusion step (\d+)/)?.[1]) >= 3
    || document.body.dataset.state !== 'running');
  assert.equal(await state(), 'running', 'the request finished before it could be cancelled');
  result.running_before_cancel = await running();
  assert.equal(result.running_before_cancel, 1);
  await page.click('#cancel');
  await page.waitForFunction(() => document.body.dataset.state === 'cancelled');
  const t0 = Date.now();
  while ((await running()) !== 0) {
    assert(Date.now() - t0 < 5000, 'the slot is still taken 5 s after cancelling');
    await new Promise((r) => setTimeout(r, 20));
  }
  result.slot_freed_ms = Date.now() - t0;
  await shoot('cancelled');

  assert.deepEqual(pageErrors, [], 'the page logged errors');
} finally {
  await writeFile(`${artifacts}/result.json`, JSON.stringify(result, null, 2));
  await browser.close();
}
step('all checks passed');
