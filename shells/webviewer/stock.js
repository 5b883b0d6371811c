// layers.glb as any glTF viewer shows it: a stock three.js scene, GLTFLoader and the file's own
// materials (unlit, baseColorTexture: the base colour; the surface layer opaque, the side layers
// blended by their opacity; no SH, no per-layer passes). For checking the file, not for viewing:
// the shells viewer is index.html. URL: ?view=I (test view I of cameras.json, its intrinsics),
// ?key=R,G,B (clear colour, 0-255). window.stock: ready, pixels() (RGB rows, top first, base64).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { pixels as readPixels } from './pixels.js';

const params = new URLSearchParams(location.search);
const cams = await fetch('cameras.json').then((r) => r.json());
const gltf = await new GLTFLoader().loadAsync('layers.glb');
const i = +(params.get('view') ?? 0);
const v = cams.views[i];
const canvas = document.getElementById('canvas');
const renderer = new THREE.WebGLRenderer({ canvas, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
renderer.setSize(cams.width, cams.height, false);
const key = (params.get('key') ?? '255,0,255').split(',').map((x) => +x / 255);
renderer.setClearColor(new THREE.Color().setRGB(...key, THREE.SRGBColorSpace), 1);
const scene = new THREE.Scene();
scene.add(gltf.scene);
// test view i: OpenCV camera-to-world in the asset's frame -> glTF's y-up frame, OpenGL axes
const toGltf = new THREE.Matrix4().fromArray(cams.world_to_gltf.flat()).transpose();
const c2w = new THREE.Matrix4().fromArray(v.c2w_opencv.flat()).transpose();
const camera = new THREE.PerspectiveCamera();
camera.matrixAutoUpdate = false;
camera.matrix.multiplyMatrices(toGltf, c2w).multiply(new THREE.Matrix4().makeScale(1, -1, -1));
camera.updateMatrixWorld(true);
const far = 4 * new THREE.Vector3().setFromMatrixPosition(camera.matrix).distanceTo(
  new THREE.Vector3(...cams.centre).applyMatrix4(toGltf));
const near = 0.005 * far, w = cams.width, h = cams.height;
camera.projectionMatrix.set(2 * v.fx / w, 0, 1 - 2 * v.cx / w, 0, 0, 2 * v.fy / h, 2 * v.cy / h - 1, 0,
                            0, 0, -(far + near) / (far - near), -2 * far * near / (far - near), 0, 0, -1, 0);
camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
renderer.render(scene, camera);

const pixels = () => readPixels(renderer.getContext());
window.stock = { ready: true, pixels };
