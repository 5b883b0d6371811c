// The baked-shells viewer: draws layers.glb (shells-bake) with three.js, the compositing rule
// of shells/bake/render.py on the GPU (or a software GL): for each layer, innermost first, a
// depth pass (the layer's nearest fragment, any facing, behind nothing drawn before) and a
// colour pass that keeps only the fragment at that depth and blends it "over":
//     C = a * clamp(base + sh . d, 0, 1) + (1 - a) * C
// with d the unit view direction in the asset's frame. The layers share one texture atlas
// (TEXCOORD_0): the material's baseColorTexture (base RGB, opacity) and three RGB images of the
// degree-1 SH axes x, y, z (the materials' extras: sh_textures, sh_scale), sampled bilinearly.
//
// URL parameters: view=I (start on test view I of cameras.json, its intrinsics and size),
// width=W&height=H (canvas size; default: the window, or the view's size), show=layers,
// msaa=0 (one sample a pixel), cull=1 (back faces of closed layers culled: not the rule
// where a ray's nearest hit on a closed layer is a back face, i.e. from inside it).
// window.shells exposes what the tests and bench/ measure (ready, setView, pixels, benchmark).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { pixels as readPixels } from './pixels.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

THREE.ColorManagement.enabled = false;  // the stored colours are display values: no conversion

const params = new URLSearchParams(location.search);
const MAX_LAYERS = 8;  // the layers-per-pixel view counts up to this many
const PALETTE = [  // layers drawn: 0, 1, ..., >= 8 (a viridis ramp)
  [0.0, 0.0, 0.0], [0.267, 0.005, 0.329], [0.283, 0.141, 0.458], [0.254, 0.265, 0.530],
  [0.207, 0.372, 0.553], [0.164, 0.471, 0.558], [0.128, 0.567, 0.551], [0.135, 0.659, 0.518],
  [0.993, 0.906, 0.144]];

const VERTEX = /* glsl */ `
precision highp float;
uniform mat4 modelViewMatrix;
uniform mat4 projectionMatrix;
uniform vec3 eye;            // camera position in the asset's frame
in vec3 position;
in vec2 uv;
out vec2 vUv;
out vec3 vToPoint;
invariant gl_Position;       // the depth and colour passes must produce the same depths
void main() {
  vUv = uv;
  vToPoint = position - eye;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

// the depth pass: the same position arithmetic (invariant), no attributes to interpolate
const DEPTH_VERTEX = /* glsl */ `
precision highp float;
uniform mat4 modelViewMatrix;
uniform mat4 projectionMatrix;
in vec3 position;
invariant gl_Position;
void main() {
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

const DEPTH_FRAGMENT = /* glsl */ `
precision highp float;
out vec4 outColor;
void main() { outColor = vec4(0.0); }`;

const FRAGMENT = /* glsl */ `
precision highp float;
uniform sampler2D baseMap;
uniform sampler2D shX;
uniform sampler2D shY;
uniform sampler2D shZ;
uniform float shScale;
in vec2 vUv;
in vec3 vToPoint;
out vec4 outColor;
void main() {
#ifdef COUNT
  outColor = vec4(1.0 / 255.0, 0.0, 0.0, 1.0);
#else
  vec3 d = normalize(vToPoint);
  vec4 base = texture(baseMap, vUv);
  float k = 255.0 / 127.0 * shScale, o = 128.0 / 127.0 * shScale;  // (byte - 128) / 127 * scale
  vec3 sh = (texture(shX, vUv).rgb * k - o) * d.x + (texture(shY, vUv).rgb * k - o) * d.y
          + (texture(shZ, vUv).rgb * k - o) * d.z;
  outColor = vec4(clamp(base.rgb + sh, 0.0, 1.0), base.a);
#endif
}`;

const canvas = document.getElementById('canvas');
const fpsText = document.getElementById('fps');
const viewSelect = document.getElementById('view');

const [asset, cams] = await Promise.all(
  ['asset.json', 'cameras.json'].map((f) => fetch(f).then((r) => r.json())));
const gltf = await new GLTFLoader().loadAsync(asset.glb, (e) => {  // the progress bar, in MB
  const total = e.lengthComputable ? e.total : asset.size_bytes;
  fpsText.textContent = `loading ${(e.loaded / 1e6).toFixed(1)} / ${(total / 1e6).toFixed(1)} MB`;
  document.getElementById('progress').value = total ? e.loaded / total : 0;
});
document.getElementById('progress').style.display = 'none';

// multisampling as the asset was fitted (shells-render --spp 4 averages a 2x2 grid of rays);
// msaa=0 draws one sample a pixel, as shells-render --spp 1
const msaa = (asset.fit?.spp ?? 1) > 1 && params.get('msaa') !== '0';
const renderer = new THREE.WebGLRenderer({ canvas, antialias: msaa, alpha: false,
                                           preserveDrawingBuffer: true, depth: true });
renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
renderer.setPixelRatio(1);
const gl = renderer.getContext();
const background = new THREE.Color().setRGB(...asset.background);

// the asset's frame -> glTF's y-up frame (the root node's rotation) and back
const root = gltf.scene.getObjectByName('asset') || gltf.scene;
gltf.scene.updateMatrixWorld(true);
const toGltf = new THREE.Matrix4().fromArray(cams.world_to_gltf.flat()).transpose();
const fromGltf = toGltf.clone().invert();
const centre = new THREE.Vector3(...cams.centre).applyMatrix4(toGltf);

// the atlas: the base colour texture of the materials, the SH images of their extras; raw
// values (no colour-space decoding), bilinear, no mipmaps, as the Python renderer samples them
let anyMaterial = null;
gltf.scene.traverse((o) => { if (o.isMesh) anyMaterial = o.material; });
const shExtras = anyMaterial.userData;
const atlas = [anyMaterial.map, ...await Promise.all(
  shExtras.sh_textures.map((i) => gltf.parser.getDependency('texture', i)))];
for (const t of atlas) {
  t.colorSpace = THREE.NoColorSpace;
  t.generateMipmaps = false;
  t.minFilter = THREE.LinearFilter;
  t.magFilter = THREE.LinearFilter;
  t.needsUpdate = true;
}

// two meshes per layer sharing its geometry: depth pass, then colour (or count) pass
const cull = params.get('cull') === '1';
const uniforms = { eye: { value: new THREE.Vector3() } };
const shared = { eye: uniforms.eye, shScale: { value: shExtras.sh_scale },
                 baseMap: { value: atlas[0] }, shX: { value: atlas[1] }, shY: { value: atlas[2] },
                 shZ: { value: atlas[3] } };
const scene = new THREE.Scene();
const colourMaterials = [];
const countMaterials = [];
const colourPasses = [];  // the second mesh of each layer: colour or count material
const layers = [];
root.traverse((o) => { if (o.isMesh) layers.push(o); });
layers.sort((a, b) => a.userData.layer - b.userData.layer);  // innermost first
let bytes = atlas.reduce((n, t) => n + t.image.width * t.image.height * 4, 0);
layers.forEach((mesh, k) => {
  const geometry = mesh.geometry;
  for (const name of Object.keys(geometry.attributes)) bytes += geometry.attributes[name].array.byteLength;
  bytes += geometry.index.array.byteLength;
  const side = cull && mesh.userData.closed ? THREE.FrontSide : THREE.DoubleSide;
  const base = { glslVersion: THREE.GLSL3, vertexShader: VERTEX, fragmentShader: FRAGMENT,
                 uniforms: shared, side, transparent: false };
  const depth = new THREE.RawShaderMaterial({ ...base, vertexShader: DEPTH_VERTEX,
                                              fragmentShader: DEPTH_FRAGMENT, colorWrite: false,
                                              depthWrite: true, depthFunc: THREE.LessEqualDepth });
  const blend = { depthWrite: false, depthFunc: THREE.EqualDepth, blending: THREE.CustomBlending,
                  blendEquation: THREE.AddEquation };
  const colour = new THREE.RawShaderMaterial({ ...base, ...blend,
    blendSrc: THREE.SrcAlphaFactor, blendDst: THREE.OneMinusSrcAlphaFactor });
  const count = new THREE.RawShaderMaterial({ ...base, ...blend, defines: { COUNT: 1 },
    blendSrc: THREE.OneFactor, blendDst: THREE.OneFactor });
  colourMaterials.push(colour);
  countMaterials.push(count);
  const m = root.matrixWorld;
  for (const [material, order] of [[depth, 2 * k], [colour, 2 * k + 1]]) {
    const pass = new THREE.Mesh(geometry, material);
    pass.matrixAutoUpdate = false;
    pass.matrix.copy(m);
    pass.renderOrder = order;
    pass.frustumCulled = false;
    scene.add(pass);
    if (material === colour) colourPasses.push(pass);
  }
});
scene.updateMatrixWorld(true);

// the layers-per-pixel view: counts into a target, then a palette on a full-screen quad
const countTarget = new THREE.WebGLRenderTarget(1, 1, { depthBuffer: true });
const quad = new THREE.Mesh(new THREE.PlaneGeometry(2, 2), new THREE.ShaderMaterial({
  uniforms: { counts: { value: countTarget.texture },
              palette: { value: PALETTE.map((c) => new THREE.Vector3(...c)) } },
  vertexShader: 'varying vec2 vUv; void main() { vUv = uv; gl_Position = vec4(position.xy, 0.0, 1.0); }',
  fragmentShader: `uniform sampler2D counts; uniform vec3 palette[${PALETTE.length}]; varying vec2 vUv;
    void main() { int n = int(texture2D(counts, vUv).r * 255.0 + 0.5);
                  gl_FragColor = vec4(palette[min(n, ${MAX_LAYERS})], 1.0); }`,
  depthTest: false, depthWrite: false }));
const quadScene = new THREE.Scene();
quadScene.add(quad);
const quadCamera = new THREE.OrthographicCamera(-1, 1, 1, -1, 0, 1);

const camera = new THREE.PerspectiveCamera(45, 1, 0.01, 100);
let show = params.get('show') === 'layers' ? 'layers' : 'colour';
let fixedView = -1;
let controls = null;

function size(width, height) {
  renderer.setSize(width, height, false);
  canvas.style.width = `${width}px`;
  canvas.style.height = `${height}px`;
  countTarget.setSize(width, height);
}

function viewPose(i) {  // OpenCV camera-to-world of the asset's frame -> three.js camera, glTF frame
  const v = cams.views[i];
  const c2w = new THREE.Matrix4().fromArray(v.c2w_opencv.flat()).transpose();
  const flip = new THREE.Matrix4().makeScale(1, -1, -1);  // OpenCV axes -> OpenGL axes
  return new THREE.Matrix4().multiplyMatrices(toGltf, c2w).multiply(flip);
}

function intrinsics(i, width, height) {  // the projection of view i, scaled to width x height
  const v = cams.views[i];
  const sx = width / cams.width, sy = height / cams.height;
  const fx = v.fx * sx, fy = v.fy * sy, cx = v.cx * sx, cy = v.cy * sy;
  const n = camera.near, f = camera.far;
  return new THREE.Matrix4().set(
    2 * fx / width, 0, 1 - 2 * cx / width, 0,
    0, 2 * fy / height, 2 * cy / height - 1, 0,
    0, 0, -(f + n) / (f - n), -2 * f * n / (f - n),
    0, 0, -1, 0);
}

function setClip(distance) {
  const radius = distance;  // the asset lies within the cameras' distance of the centre
  camera.near = Math.max(1e-3, 0.02 * radius);
  camera.far = 4 * radius;
}

function setView(i) {  // -1: free orbit; otherwise test view i with its intrinsics
  fixedView = i;
  const width = +params.get('width') || (i >= 0 ? cams.width : window.innerWidth);
  const height = +params.get('height') || (i >= 0 ? cams.height : window.innerHeight);
  size(width, height);
  const pose = viewPose(Math.max(i, 0));
  const position = new THREE.Vector3().setFromMatrixPosition(pose);
  setClip(position.distanceTo(centre));
  if (i >= 0) {
    if (controls) controls.enabled = false;
    camera.matrixAutoUpdate = false;
    camera.matrix.copy(pose);
    camera.updateMatrixWorld(true);
    camera.projectionMatrix.copy(intrinsics(i, width, height));
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  } else {
    camera.matrixAutoUpdate = true;
    camera.position.copy(position);
    camera.up.set(0, 1, 0);
    camera.fov = 2 * Math.atan(cams.height / (2 * cams.views[0].fy)) * 180 / Math.PI;
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
    if (!controls) controls = new OrbitControls(camera, canvas);
    controls.enabled = true;
    controls.target.copy(centre);
    controls.update();
  }
}

function render() {
  camera.updateMatrixWorld(true);
  uniforms.eye.value.setFromMatrixPosition(camera.matrixWorld).applyMatrix4(fromGltf);
  const counting = show === 'layers';
  colourPasses.forEach((pass, k) => {
    pass.material = counting ? countMaterials[k] : colourMaterials[k];
  });
  if (counting) {
    renderer.setRenderTarget(countTarget);
    renderer.setClearColor(0x000000, 1);
    renderer.clear();
    renderer.render(scene, camera);
    renderer.setRenderTarget(null);
    renderer.render(quadScene, quadCamera);
  } else {
    renderer.setClearColor(background, 1);
    renderer.render(scene, camera);
  }
}

function finish() {  // wait for the GPU: a one-pixel read back
  const px = new Uint8Array(4);
  gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
}

const pixels = () => readPixels(gl);  // the canvas, for scripts

function benchmark(frames = 60, width = cams.width, height = cams.height) {
  // a synchronous orbit of `frames` frames at the view-0 distance and elevation; ms per frame
  params.set('width', width);
  params.set('height', height);
  setView(-1);
  const start = new THREE.Vector3().setFromMatrixPosition(viewPose(0)).sub(centre);
  const r = start.length(), el = Math.asin(start.y / r), az0 = Math.atan2(start.z, start.x);
  render(); finish();  // compile the shaders, upload the buffers
  const ms = [];
  for (let k = 0; k < frames; k++) {
    const az = az0 + 2 * Math.PI * k / frames;
    camera.position.set(centre.x + r * Math.cos(el) * Math.cos(az), centre.y + r * Math.sin(el),
                        centre.z + r * Math.cos(el) * Math.sin(az));
    camera.lookAt(centre);
    const t0 = performance.now();
    render(); finish();
    ms.push(performance.now() - t0);
  }
  const sorted = [...ms].sort((a, b) => a - b);
  return { frames, width, height, median_ms: sorted[Math.floor(frames / 2)], ms, msaa, cull,
           renderer: gl.getParameter(gl.VERSION) + ' / ' + (() => {
             const ext = gl.getExtension('WEBGL_debug_renderer_info');
             return ext ? gl.getParameter(ext.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
           })() };
}

// the HUD: fps of the interactive loop, colour / layers per pixel, camera
cams.views.forEach((_, i) => viewSelect.add(new Option(`test view ${i}`, String(i))));
viewSelect.addEventListener('change', () => { setView(+viewSelect.value); });
for (const input of document.querySelectorAll('input[name=show]')) {
  input.checked = input.value === show;
  input.addEventListener('change', () => { show = input.value; legend(); });
}
function legend() {
  const el = document.getElementById('legend');
  el.style.display = show === 'layers' ? 'block' : 'none';
  el.innerHTML = 'layers drawn: ' + PALETTE.map((c, n) =>
    `<span style="background:rgb(${c.map((x) => Math.round(255 * x)).join(',')})"></span>${n === MAX_LAYERS ? '≥' + n : n} `).join('');
}
legend();

const start = params.has('view') ? +params.get('view') : -1;
viewSelect.value = String(start);
setView(start);
window.addEventListener('resize', () => { if (fixedView < 0 && !params.has('width')) setView(-1); });

let last = performance.now(), smooth = 0;
const triangles = layers.reduce((n, m) => n + m.geometry.index.count / 3, 0);
function hud(ms) {
  fpsText.textContent = `${(1000 / ms).toFixed(1)} fps · ${layers.length} layers · ` +
    `${(triangles / 1e3).toFixed(1)} k triangles · atlas ${atlas[0].image.width}×` +
    `${atlas[0].image.height} · ${(bytes / 1e6).toFixed(1)} MB on the GPU`;
}
function loop() {
  render();
  const now = performance.now();
  smooth = smooth ? 0.9 * smooth + 0.1 * (now - last) : now - last;
  last = now;
  hud(smooth);
  if (!window.shells.paused) requestAnimationFrame(loop);
}
function frame() {  // one timed frame (paused pages: scripts, screenshots); its ms
  const t0 = performance.now();
  render(); finish();
  const ms = performance.now() - t0;
  hud(ms);
  return ms;
}
window.shells = { ready: true, paused: params.has('paused'), setView,
                  setShow: (s) => { show = s; legend(); }, render, finish, frame, pixels,
                  benchmark, layers: layers.length, triangles };
if (!window.shells.paused) requestAnimationFrame(loop);
else render();
