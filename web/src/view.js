// The 3D view: the streamed faces (flat shaded, an optional wireframe over them), the input
// points faint beside them, and orbit/zoom/pan, with the input's up axis up. It renders only
// when something changed.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

export const BACKGROUND = 0x20242b;

/** The turn (Euler angles about x, y, z) that stands an input with this axis up on +y. */
const STAND_UP = {
  z: [-Math.PI / 2, 0, 0],
  '-z': [Math.PI / 2, 0, 0],
  x: [0, 0, Math.PI / 2],
  '-x': [0, 0, -Math.PI / 2],
  '-y': [Math.PI, 0, 0],
};

export class View {
  constructor(canvas) {
    // preserveDrawingBuffer keeps the last frame readable (tests and screenshots read it).
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1000);
    this.camera.add(new THREE.DirectionalLight(0xffffff, 2.2).translateX(1).translateY(2).translateZ(3));
    this.scene.add(this.camera, new THREE.HemisphereLight(0xffffff, 0x445066, 1.2));
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.addEventListener('change', () => this.redraw());

    this.faces = new THREE.BufferGeometry();
    this.faceCount = 0;
    this.capacity = 0;
    const surface = new THREE.MeshStandardMaterial({
      vertexColors: true,
      flatShading: true,
      side: THREE.DoubleSide,
      roughness: 0.8,
      polygonOffset: true,
      polygonOffsetFactor: 1,
      polygonOffsetUnits: 1,
    });
    const wire = new THREE.MeshBasicMaterial({ color: 0x0b0d10, wireframe: true });
    this.surface = new THREE.Mesh(this.faces, surface);
    this.wireframe = new THREE.Mesh(this.faces, wire);
    this.wireframe.visible = false;
    this.points = new THREE.Points(
      new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ color: 0xaab4c8, size: 2, sizeAttenuation: false, transparent: true, opacity: 0.45 }),
    );
    // Faces and points stay in the caller's coordinates (downloads read them as they are);
    // their group is turned to show the caller's up axis up.
    this.content = new THREE.Group().add(this.surface, this.wireframe, this.points);
    this.scene.add(this.content);
    this.frame(new THREE.Sphere(new THREE.Vector3(), 1.5));

    new ResizeObserver(() => this.resize()).observe(canvas);
    this.resize();
  }

  /** Shows an input's points (a flat position array), or none, and frames them. */
  showInput(positions) {
    this.points.geometry.dispose();
    this.points.geometry = new THREE.BufferGeometry();
    if (positions) {
      this.points.geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
      this.points.geometry.computeBoundingSphere();
    }
    this.frameInput();
  }

  /** Turns the view so that the input's `axis` (y, z, x or one negated; '' is y) is up. */
  setUp(axis) {
    this.content.rotation.set(...(STAND_UP[axis] ?? [0, 0, 0]));
    this.content.updateMatrixWorld(true);
    this.frameInput();
  }

  frameInput() {
    const sphere = this.points.geometry.boundingSphere
      // An image's mesh comes in the model's frame, centred in [-1, 1].
      ?? new THREE.Sphere(new THREE.Vector3(), Math.sqrt(3));
    this.frame(sphere.clone().applyMatrix4(this.content.matrixWorld));
    this.redraw();
  }

  /** Empties the face buffer, with room for `expected` faces. */
  clearFaces(expected) {
    this.faceCount = 0;
    this.allocate(Math.max(expected, 64));
    this.redraw();
  }

  /** Appends one face: three [x, y, z] corners. */
  addFace(corners) {
    if (this.faceCount === this.capacity) this.allocate(this.capacity * 2);
    const position = this.faces.getAttribute('position');
    const normal = this.faces.getAttribute('normal');
    const color = this.faces.getAttribute('color');
    const [a, b, c] = corners.map((p) => new THREE.Vector3(...p));
    const n = new THREE.Vector3().subVectors(c, b).cross(new THREE.Vector3().subVectors(a, b)).normalize();
    // Neighbouring faces get well-separated hues (golden-ratio steps), so each new face shows.
    const hue = (this.faceCount * 0.618034) % 1;
    const rgb = new THREE.Color().setHSL(hue, 0.45, 0.62, THREE.SRGBColorSpace);
    for (let k = 0; k < 3; k++) {
      const i = this.faceCount * 3 + k;
      position.setXYZ(i, ...corners[k]);
      normal.setXYZ(i, n.x, n.y, n.z);
      color.setXYZ(i, rgb.r, rgb.g, rgb.b);
    }
    this.faceCount++;
    for (const attribute of [position, normal, color]) {
      attribute.addUpdateRange(0, this.faceCount * 9);
      attribute.needsUpdate = true;
    }
    this.faces.setDrawRange(0, this.faceCount * 3);
    this.redraw();
  }

  /** The faces so far, as a flat array of corner positions (three per face). */
  facePositions() {
    return this.faces.getAttribute('position').array.slice(0, this.faceCount * 9);
  }

  setWireframe(on) {
    this.wireframe.visible = on;
    this.redraw();
  }

  setInputVisible(on) {
    this.points.visible = on;
    this.redraw();
  }

  allocate(capacity) {
    const old = this.faces.getAttribute('position') ? this.facePositions().length : 0;
    const faces = new THREE.BufferGeometry();
    for (const name of ['position', 'normal', 'color']) {
      const array = new Float32Array(capacity * 9);
      const previous = this.faces.getAttribute(name);
      if (previous) array.set(previous.array.subarray(0, old));
      faces.setAttribute(name, new THREE.BufferAttribute(array, 3).setUsage(THREE.DynamicDrawUsage));
    }
    faces.setDrawRange(0, this.faceCount * 3);
    // The faces never leave the input's neighbourhood: a fixed sphere saves recomputing it.
    faces.boundingSphere = new THREE.Sphere(new THREE.Vector3(), Infinity);
    this.faces.dispose();
    this.faces = faces;
    this.surface.geometry = faces;
    this.wireframe.geometry = faces;
    this.capacity = capacity;
  }

  frame(sphere) {
    const distance = sphere.radius / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2));
    const direction = new THREE.Vector3(0.6, 0.45, 1).normalize();
    this.controls.target.copy(sphere.center);
    this.camera.position.copy(sphere.center).addScaledVector(direction, distance * 1.05);
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    this.camera.updateProjectionMatrix();
    this.controls.update();
  }

  resize() {
    const canvas = this.renderer.domElement;
    const width = canvas.clientWidth || 1;
    const height = canvas.clientHeight || 1;
    this.renderer.setSize(width, height, false);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.redraw();
  }

  redraw() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.renderer.render(this.scene, this.camera);
    });
  }
}
