// The streamed faces as a file: corners that coincide are merged into shared vertices, then
// three.js's exporters write GLB, OBJ, PLY or STL.

import * as THREE from 'three';
import { GLTFExporter } from 'three/addons/exporters/GLTFExporter.js';
import { OBJExporter } from 'three/addons/exporters/OBJExporter.js';
import { PLYExporter } from 'three/addons/exporters/PLYExporter.js';
import { STLExporter } from 'three/addons/exporters/STLExporter.js';
import { mergeVertices } from 'three/addons/utils/BufferGeometryUtils.js';

const TYPES = {
  glb: 'model/gltf-binary',
  obj: 'model/obj',
  ply: 'application/ply',
  stl: 'model/stl',
};

/** The faces (a flat array of corner positions) as a file in `format`: a Blob. */
export async function exportFaces(positions, format) {
  const soup = new THREE.BufferGeometry();
  soup.setAttribute('position', new THREE.BufferAttribute(positions, 3));
  const mesh = new THREE.Mesh(mergeVertices(soup), new THREE.MeshStandardMaterial());
  mesh.name = 'meshstream';
  let data;
  switch (format) {
    case 'glb':
      data = await new GLTFExporter().parseAsync(mesh, { binary: true });
      break;
    case 'obj':
      data = new OBJExporter().parse(mesh);
      break;
    case 'ply':
      data = await new Promise((done) => new PLYExporter().parse(mesh, done, { binary: true }));
      break;
    case 'stl':
      data = new STLExporter().parse(mesh, { binary: true });
      break;
    default:
      throw new Error(`no exporter for ${format}`);
  }
  return new Blob([data], { type: TYPES[format] });
}

/** Hands a Blob to the browser as a download named `name`. */
export function save(blob, name) {
  const link = document.createElement('a');
  link.href = URL.createObjectURL(blob);
  link.download = name;
  link.click();
  setTimeout(() => URL.revokeObjectURL(link.href), 60_000);
}
