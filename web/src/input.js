// What the user gives the page: a mesh or point cloud (sent to /reconstruct, its points shown
// beside the result) or an image (sent to /generate, shown as a thumbnail).

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OBJLoader } from 'three/addons/loaders/OBJLoader.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';
import { STLLoader } from 'three/addons/loaders/STLLoader.js';

const IMAGE_TYPES = { png: 'image/png', jpg: 'image/jpeg', jpeg: 'image/jpeg', webp: 'image/webp' };
const MESH_TYPES = {
  ply: 'application/ply',
  obj: 'model/obj',
  stl: 'model/stl',
  glb: 'model/gltf-binary',
};

/**
 * The request for a file: its endpoint and content type. A file of another name goes to
 * /reconstruct as application/octet-stream, where the server sniffs its format or says why it
 * cannot read it.
 */
export function describe(file) {
  const extension = file.name.split('.').pop().toLowerCase();
  if (IMAGE_TYPES[extension] || file.type.startsWith('image/')) {
    return {
      kind: 'image',
      path: '/generate',
      contentType: IMAGE_TYPES[extension] || file.type,
    };
  }
  return {
    kind: 'points',
    path: '/reconstruct',
    contentType: MESH_TYPES[extension] || 'application/octet-stream',
    extension,
  };
}

/**
 * The vertex positions of a mesh or point cloud file (a flat Float32Array in the file's
 * coordinates, as the server answers in them), or null when the page cannot read it: the
 * server still gets the file and gives its own verdict.
 */
export async function previewPoints(bytes, extension) {
  try {
    switch (extension) {
      case 'ply':
        return new PLYLoader().parse(bytes).getAttribute('position').array;
      case 'stl':
        return new STLLoader().parse(bytes).getAttribute('position').array;
      case 'obj':
        return positionsOf(new OBJLoader().parse(new TextDecoder().decode(bytes)));
      case 'glb':
        return positionsOf((await new GLTFLoader().parseAsync(bytes, '')).scene);
      default:
        return null;
    }
  } catch {
    return null;
  }
}

/** Every mesh's positions in an object tree, in world coordinates. */
function positionsOf(root) {
  root.updateMatrixWorld(true);
  const all = [];
  const v = new THREE.Vector3();
  root.traverse((node) => {
    const position = node.geometry?.getAttribute('position');
    if (!position) return;
    for (let i = 0; i < position.count; i++) {
      v.fromBufferAttribute(position, i).applyMatrix4(node.matrixWorld);
      all.push(v.x, v.y, v.z);
    }
  });
  return all.length ? new Float32Array(all) : null;
}
