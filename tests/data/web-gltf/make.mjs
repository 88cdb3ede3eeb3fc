// Writes each INPUT made small for the web by glTF-Transform, as `gltf-transform` would, to
// OUT_DIR under the same name: MODE is quantized (KHR_mesh_quantization), meshopt
// (EXT_meshopt_compression, quantized first) or draco (KHR_draco_mesh_compression, Google's
// encoder). Usage: node make.mjs MODE OUT_DIR INPUT... (next to the packages make.sh installs;
// scripts/check-web-gltf.sh runs it over the dev split)
import { basename, join } from 'node:path';
import { NodeIO } from '@gltf-transform/core';
import { ALL_EXTENSIONS } from '@gltf-transform/extensions';
import { quantize, meshopt, draco } from '@gltf-transform/functions';
import draco3d from 'draco3dgltf';
import { MeshoptEncoder, MeshoptDecoder } from 'meshoptimizer';

const [mode, outDir, ...inputs] = process.argv.slice(2);
await MeshoptEncoder.ready;
await MeshoptDecoder.ready;
const io = new NodeIO().registerExtensions(ALL_EXTENSIONS).registerDependencies({
  'draco3d.encoder': await draco3d.createEncoderModule(),
  'draco3d.decoder': await draco3d.createDecoderModule(),
  'meshopt.encoder': MeshoptEncoder,
  'meshopt.decoder': MeshoptDecoder,
});
const steps = {
  quantized: [quantize()],
  meshopt: [meshopt({ encoder: MeshoptEncoder, level: 'high' })],
  draco: [draco()],
}[mode];
if (!steps) throw new Error(`unknown mode ${mode}`);
for (const input of inputs) {
  const doc = await io.read(input);
  await doc.transform(...steps);
  await io.write(join(outDir, basename(input)), doc);
}
