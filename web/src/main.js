// The page: pick or drop an input, stream its faces into the view, cancel, download.

import { ApiError, serverInfo, streamRequest } from './api.js';
import { exportFaces, save } from './download.js';
import { describe, previewPoints } from './input.js';
import { View } from './view.js';

const $ = (id) => document.getElementById(id);
const view = new View($('canvas'));
const OPTIONS = {
  points: ['max_faces', 'temperature', 'seed', 'candidates', 'up'],
  image: ['max_faces', 'temperature', 'seed', 'steps', 'guidance', 'framing'],
};

let input = null; // { file, kind, path, contentType, extension }
let running = null; // the AbortController of the request in flight
// A points request asks for the server's whole-mesh answer (best of its candidates, welded and
// fitted), with the first candidate's faces streamed as drafts while it is made: the page
// shows the model decoding, then the answer. From /v1/info.
let wholeMesh = { candidates: '', weld_radius: '', fit_rounds: '' };

function setState(state) {
  document.body.dataset.state = state;
  $('run').disabled = !input || state === 'running';
  $('cancel').disabled = state !== 'running';
  for (const button of document.querySelectorAll('#downloads button')) {
    button.disabled = state === 'running' || view.faceCount === 0;
  }
}

/** The done event's `quality` as a line: what the answer says of its build and closeness. */
function describeQuality(q) {
  const parts = q.parts === 1 ? '1 part' : `${q.parts} parts`;
  const build = q.watertight
    ? 'watertight'
    : `${q.boundary_edges} of ${q.edges} edges open, ${q.non_manifold_edges} non-manifold`;
  const distance = q.input_chamfer === undefined ? '' : `, Chamfer distance to the input ${q.input_chamfer.toFixed(3)}`;
  return `${parts}, ${build}${distance}`;
}

function showError(text) {
  $('error').textContent = text;
  $('error').hidden = !text;
}

async function choose(file) {
  if (running) running.abort();
  input = { file, ...describe(file) };
  // The picker shows its own last pick: clear it when the input came from elsewhere.
  if ($('file').files[0] !== file) $('file').value = '';
  $('input-name').textContent = `${file.name} (${(file.size / 1024).toFixed(1)} KB)`;
  const thumbnail = $('thumbnail');
  URL.revokeObjectURL(thumbnail.src);
  thumbnail.hidden = input.kind !== 'image';
  // An image's mesh comes in the model's frame, y up.
  view.setUp(input.kind === 'points' ? $('up').value : '');
  if (input.kind === 'image') {
    thumbnail.src = URL.createObjectURL(file);
    view.showInput(null);
  } else {
    const preview = await previewPoints(await file.arrayBuffer(), input.extension);
    view.showInput(preview?.positions);
    if (preview) {
      const count = preview.positions.length / 3;
      $('input-name').textContent += preview.sampled
        ? `: ${count} points drawn on its surface`
        : `: ${count} points`;
    }
  }
  await run();
}

async function run() {
  if (running) running.abort();
  const controller = new AbortController();
  running = controller;
  showError('');
  view.clearFaces(Number($('max_faces').value) || Number($('max_faces').max) || 1024);
  $('face-count').textContent = '0';
  setState('running');
  const options = Object.fromEntries(OPTIONS[input.kind].map((name) => [name, $(name).value]));
  if (input.kind === 'points') {
    Object.assign(options, {
      candidates: options.candidates || wholeMesh.candidates,
      weld_radius: wholeMesh.weld_radius,
      fit_rounds: wholeMesh.fit_rounds,
      drafts: true,
    });
  }
  const started = performance.now();
  let firstFace = null;
  let answering = false; // the answer's faces have begun (they replace the drafts)
  let diffusion = '';
  const progress = () => {
    const parts = [diffusion];
    if (firstFace !== null) {
      const seconds = (performance.now() - firstFace) / 1000;
      const rate = seconds > 0 ? (view.faceCount - 1) / seconds : 0;
      parts.push(
        answering ? `${view.faceCount} faces` : `draft: ${view.faceCount} faces of the first candidate`,
        `${rate.toFixed(1)} faces/s`,
        `first face after ${((firstFace - started) / 1000).toFixed(2)} s`,
      );
    } else if (!diffusion) {
      parts.push('waiting for the first face…');
    }
    $('progress').textContent = parts.filter(Boolean).join(' · ');
  };
  progress();
  try {
    const done = await streamRequest({
      path: input.path,
      body: input.file,
      contentType: input.contentType,
      options,
      signal: controller.signal,
      onEvent(event) {
        if (event.type === 'progress') {
          diffusion = `diffusion step ${event.step} of ${event.steps}`;
        } else if (event.type === 'draft' || event.type === 'face') {
          firstFace ??= performance.now();
          if (event.type === 'face' && !answering) {
            // The answer replaces the drafts at once: its faces come together.
            answering = true;
            view.clearFaces(view.faceCount);
          }
          view.addFace(event.vertices);
          $('face-count').textContent = String(view.faceCount);
        }
        progress();
      },
    });
    progress();
    if (done.faces === 0) {
      // What a whole mesh gets as a 422 (no_faces): said as plainly here.
      $('progress').textContent = '';
      showError(`The model produced no faces for this input (${done.finish_reason}); another seed may.`);
      setState('error');
      return;
    }
    const total = (done.total_ms / 1000).toFixed(2);
    $('progress').textContent += `\nDone: ${done.faces} faces (${done.finish_reason}) in ${total} s on the server.`;
    if (done.quality) $('progress').textContent += `\nThe mesh: ${describeQuality(done.quality)}.`;
    setState('done');
  } catch (error) {
    if (controller.signal.aborted) {
      if (running === controller) {
        $('progress').textContent += '\nCancelled.';
        setState('cancelled');
      }
      return;
    }
    $('progress').textContent = '';
    showError(error instanceof ApiError ? error.toString() : `The request failed: ${error.message}`);
    setState('error');
  } finally {
    if (running === controller) running = null;
  }
}

async function loadExample(name) {
  try {
    const response = await fetch(`/ui/examples/${name}`);
    if (!response.ok) throw new Error(`${response.status} ${response.statusText}`);
    const blob = await response.blob();
    await choose(new File([blob], name, { type: blob.type }));
  } catch (error) {
    showError(`Cannot load the example ${name}: ${error.message}`);
  }
}

async function showServerInfo() {
  try {
    const info = await serverInfo();
    const { limits, defaults } = info;
    const image = info.image_model;
    const set = (id, placeholder, max) => {
      $(id).placeholder = placeholder;
      if (max !== undefined) $(id).max = max;
    };
    set('max_faces', limits.max_faces, limits.max_faces);
    // f32 defaults come as their nearest f64 (1.2000000476837158): shown as written.
    set('temperature', Number(defaults.temperature.toPrecision(6)));
    set('seed', 0);
    wholeMesh = {
      candidates: defaults.candidates.whole_mesh,
      weld_radius: defaults.weld_radius.whole_mesh,
      fit_rounds: defaults.fit_rounds.whole_mesh,
    };
    set('candidates', wholeMesh.candidates);
    if (image) {
      set('steps', image.default_steps, info.engine.max_diffusion_steps);
      set('guidance', Number(image.default_guidance.toPrecision(6)));
      $('framing-default').textContent = `the server's (${image.default_framing})`;
    }
    const mb = (limits.max_body_bytes / 2 ** 20).toFixed(0);
    $('server').textContent =
      `meshstream ${info.version}: up to ${limits.max_faces} faces, ${limits.max_points} points, ` +
      `${mb} MiB a file; ${image ? 'images accepted' : 'no image model (images are refused)'}.`;
  } catch (error) {
    $('server').textContent = `The server did not say its limits: ${error}`;
  }
}

$('file').addEventListener('change', () => {
  if ($('file').files[0]) choose($('file').files[0]);
});
const drop = $('drop');
document.addEventListener('dragover', (event) => {
  event.preventDefault();
  drop.classList.add('over');
});
document.addEventListener('dragleave', () => drop.classList.remove('over'));
document.addEventListener('drop', (event) => {
  event.preventDefault();
  drop.classList.remove('over');
  const file = event.dataTransfer.files[0];
  if (file) choose(file);
});
for (const button of document.querySelectorAll('[data-example]')) {
  button.addEventListener('click', () => {
    // Each example says which of its axes is up (the pine tree's source puts z up).
    $('up').value = button.dataset.up ?? '';
    loadExample(button.dataset.example);
  });
}
$('run').addEventListener('click', () => run());
$('up').addEventListener('change', () => {
  if (input?.kind !== 'image') view.setUp($('up').value);
});
$('cancel').addEventListener('click', () => running?.abort());
$('wireframe').addEventListener('change', () => view.setWireframe($('wireframe').checked));
$('show-input').addEventListener('change', () => view.setInputVisible($('show-input').checked));
for (const button of document.querySelectorAll('[data-format]')) {
  button.addEventListener('click', async () => {
    const format = button.dataset.format;
    const stem = input.file.name.replace(/\.[^.]*$/, '');
    save(await exportFaces(view.facePositions(), format), `${stem}-meshstream.${format}`);
  });
}
showServerInfo();
setState('idle');
