// What the user gives the page: a mesh or point cloud (sent to /reconstruct, its points shown
// beside the result) or an image (sent to /generate, shown as a thumbnail).

import * as THREE from 'three';
import { DRACOLoader } from 'three/addons/loaders/DRACOLoader.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import { OBJLoader } from 'three/addons/loaders/OBJLoader.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';
import { STLLoader } from 'three/addons/loaders/STLLoader.js';
import { MeshSurfaceSampler } from 'three/addons/math/MeshSurfaceSampler.js';

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

/** Points drawn on each mesh's surface, as the server samples a mesh it is sent. */
const SAMPLES_PER_MESH = 4096;

/**
 * The input's points in the file's coordinates (the server answers in them): `positions`, a
 * flat Float32Array, a point cloud's own or points drawn on a mesh's surface (`sampled`). Null
 * when the page cannot read the file: the server still gets it and gives its own verdict.
 */
export async function previewPoints(bytes, extension) {
  try {
    const root = await load(bytes, extension);
    return root ? pointsOf(root) : null;
  } catch {
    return null;
  }
}

async function load(bytes, extension) {
  switch (extension) {
    case 'ply': {
      const geometry = new PLYLoader().parse(bytes);
      return geometry.index ? new THREE.Mesh(geometry) : new THREE.Points(geometry);
    }
    case 'stl':
      return new THREE.Mesh(new STLLoader().parse(bytes));
    case 'obj':
      return new OBJLoader().parse(new TextDecoder().decode(bytes));
    case 'glb':
      // Quantized, meshopt- and Draco-compressed files preview too; Draco's decoder (served
      // under /ui/draco/) loads only when a file needs it.
      return (await gltfLoader().parseAsync(bytes, '')).scene;
    default:
      return null;
  }
}

let loader = null;

function gltfLoader() {
  loader ??= new GLTFLoader()
    .setMeshoptDecoder(MeshoptDecoder)
    .setDRACOLoader(new DRACOLoader().setDecoderPath('/ui/draco/'));
  return loader;
}

/** Every mesh's surface points and every point cloud's points, in world coordinates. */
function pointsOf(root) {
  root.updateMatrixWorld(true);
  const all = [];
  const v = new THREE.Vector3();
  let sampled = false;
  root.traverse((node) => {
    const position = node.geometry?.getAttribute('position');
    if (!position) return;
    if (node.isMesh) {
      sampled = true;
      const sampler = new MeshSurfaceSampler(node).build();
      for (let i = 0; i < SAMPLES_PER_MESH; i++) {
        sampler.sample(v);
        v.applyMatrix4(node.matrixWorld);
        all.push(v.x, v.y, v.z);
      }
    } else {
      for (let i = 0; i < position.count; i++) {
        v.fromBufferAttribute(position, i).applyMatrix4(node.matrixWorld);
        all.push(v.x, v.y, v.z);
      }
    }
  });
  return all.every(Number.isFinite) && all.length
    ? { positions: new Float32Array(all), sampled }
    : null;
}
