// The report's 3D viewer (viewer.html): the scan and the fitted bodies of a recording, in
// the scene's world frame (z up). Orbit with the mouse, step and play through the frames,
// toggle the fit, the baseline, the flag colours and an x-ray of the scan.
//
// Bundled with three.js into one classic script (npm run build), so that the page also
// opens from disk, where browsers refuse ES modules and fetch(): there each GLB is read
// from its twin 3d/<name>.glb.js, which hands the same bytes (base64) to proxGlb().
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

const config = JSON.parse(document.getElementById("viewer-config").textContent);
const status = document.getElementById("status");
const fromDisk = location.protocol === "file:";
const loader = new GLTFLoader();
const pending = new Map(); // twin scripts waiting for their bytes

window.proxGlb = (address, base64) => { // called by a twin script, with its own address
  const bytes = Uint8Array.from(atob(base64), (c) => c.charCodeAt(0));
  const done = pending.get(address);
  if (done) { pending.delete(address); done(bytes.buffer); }
};

function readBytes(path) {
  if (!fromDisk) {
    return fetch(path).then((r) => {
      if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
      return r.arrayBuffer();
    });
  }
  return new Promise((resolve, reject) => {
    const script = document.createElement("script");
    script.src = `${path}.js`;
    pending.set(script.src, resolve); // the resolved address, as the twin sees it
    script.onerror = () => reject(new Error(`${path}.js could not be read`));
    document.head.appendChild(script);
  });
}

function loadMesh(path) {
  return readBytes(path).then((buffer) => new Promise((resolve, reject) => {
    loader.parse(buffer, "", (gltf) => {
      let mesh = null;
      gltf.scene.traverse((o) => { if (o.isMesh && !mesh) mesh = o; });
      if (!mesh) reject(new Error(`${path}: no mesh`)); else resolve(mesh);
    }, reject);
  }));
}

const canvas = document.getElementById("viewer");
let renderer;
try {
  renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
} catch (error) {
  status.textContent = "This browser cannot draw WebGL: " + error.message;
  throw error;
}
renderer.setPixelRatio(window.devicePixelRatio || 1);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xf4f4f2);
scene.add(new THREE.HemisphereLight(0xffffff, 0x606060, 2.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(2, -3, 6);
scene.add(sun);

const camera = new THREE.PerspectiveCamera(config.fov_y, 16 / 9, 0.05, 100);
camera.up.set(0, 0, 1);
const pose = config.camera_pose; // OpenCV camera-to-world, rows
camera.position.set(pose[0][3], pose[1][3], pose[2][3]);
const controls = new OrbitControls(camera, canvas);
controls.target.set(...config.target);
controls.update();

function resize() {
  const width = canvas.clientWidth, height = canvas.clientHeight;
  renderer.setSize(width, height, false);
  camera.aspect = width / height;
  camera.updateProjectionMatrix();
}

const ui = {
  slider: document.getElementById("frame"),
  label: document.getElementById("frame-name"),
  stats: document.getElementById("frame-stats"),
  play: document.getElementById("play"),
  fit: document.getElementById("show-fit"),
  baseline: document.getElementById("show-baseline"),
  flags: document.getElementById("show-flags"),
  xray: document.getElementById("xray"),
};
const bodies = { fit: new Map(), baseline: new Map() }; // frame index -> promise of a mesh
const shown = { fit: null, baseline: null };
let scan = null, current = 0, timer = null;

function styleBody(mesh, colour) {
  mesh.material = new THREE.MeshStandardMaterial({ roughness: 0.75, metalness: 0 });
  mesh.userData.colour = new THREE.Color(...colour);
  applyFlags(mesh);
}

function applyFlags(mesh) {
  const flags = ui.flags.checked && mesh.geometry.hasAttribute("color");
  mesh.material.vertexColors = flags;
  mesh.material.color = flags ? new THREE.Color(1, 1, 1) : mesh.userData.colour;
  mesh.material.needsUpdate = true;
}

function body(run, index) {
  const cache = bodies[run];
  if (!cache.has(index)) {
    const path = `3d/${run === "fit" ? "" : "baseline/"}${encodeURIComponent(config.frames[index])}.glb`;
    cache.set(index, loadMesh(path).then((mesh) => {
      styleBody(mesh, config.colours[run]);
      return mesh;
    }));
  }
  return cache.get(index);
}

function draw() {
  renderer.render(scene, camera);
}

async function show(index) {
  current = index;
  ui.slider.value = index;
  ui.label.textContent = config.frames[index];
  ui.stats.textContent = config.stats[index];
  for (const run of ["fit", "baseline"]) {
    const wanted = run === "fit" ? ui.fit.checked : (config.baseline && ui.baseline.checked);
    const mesh = wanted ? await body(run, index) : null;
    if (index !== current) return; // a later step overtook this one
    if (shown[run] !== mesh) {
      if (shown[run]) scene.remove(shown[run]);
      if (mesh) scene.add(mesh);
      shown[run] = mesh;
    }
  }
  draw();
  if (index + 1 < config.frames.length) body("fit", index + 1); // read ahead
}

function setXray() {
  if (!scan) return;
  scan.material.transparent = ui.xray.checked;
  scan.material.opacity = ui.xray.checked ? 0.3 : 1;
  scan.material.depthWrite = !ui.xray.checked;
  scan.material.needsUpdate = true;
  draw();
}

function togglePlay() {
  if (timer) {
    clearInterval(timer);
    timer = null;
    ui.play.textContent = "play";
    return;
  }
  ui.play.textContent = "pause";
  timer = setInterval(() => show((current + 1) % config.frames.length), 1000 / config.fps);
}

ui.slider.max = config.frames.length - 1;
ui.slider.addEventListener("input", () => show(Number(ui.slider.value)));
document.getElementById("previous").addEventListener("click",
  () => show(Math.max(0, current - 1)));
document.getElementById("next").addEventListener("click",
  () => show(Math.min(config.frames.length - 1, current + 1)));
ui.play.addEventListener("click", togglePlay);
for (const box of [ui.fit, ui.baseline]) box.addEventListener("change", () => show(current));
ui.flags.addEventListener("change", () => {
  for (const cache of Object.values(bodies)) {
    for (const promise of cache.values()) promise.then(applyFlags);
  }
  Promise.all([...bodies.fit.values(), ...bodies.baseline.values()]).then(draw);
});
ui.xray.addEventListener("change", setXray);
document.addEventListener("keydown", (event) => {
  if (event.target.tagName === "INPUT" && event.target.type === "range") return;
  if (event.key === "ArrowRight") show(Math.min(config.frames.length - 1, current + 1));
  else if (event.key === "ArrowLeft") show(Math.max(0, current - 1));
  else if (event.key === " ") { event.preventDefault(); togglePlay(); }
});
controls.addEventListener("change", draw);
window.addEventListener("resize", () => { resize(); draw(); });
resize();

loadMesh("3d/scene.glb").then((mesh) => {
  mesh.material = new THREE.MeshStandardMaterial({
    roughness: 0.9, metalness: 0, side: THREE.DoubleSide,
    vertexColors: mesh.geometry.hasAttribute("color"),
    color: mesh.geometry.hasAttribute("color") ? 0xffffff : new THREE.Color(...config.colours.scene),
  });
  mesh.renderOrder = 1; // after the bodies, so that its x-ray shows them
  scan = mesh;
  scene.add(mesh);
  setXray();
  return show(0);
}).then(() => {
  status.textContent = "";
  document.body.dataset.viewerReady = "1";
}).catch((error) => {
  status.textContent = "Could not load the 3D files: " + error.message;
  document.body.dataset.viewerError = error.message;
});
