// uvatar viewer: three.js renders the skinned GLB; onnxruntime-web synthesizes texture and
// displacement for the current pose; a motion plays, sliders pose joints, the camera orbits.
import * as THREE from 'three';
import { GLTFLoader } from 'three/examples/jsm/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/examples/jsm/controls/OrbitControls.js';
import { Generator, loadOrt } from './generator.js';
import { makeAvatarMaterial, makeColorTexture, makeDisplacementTexture, uploadMaps } from './material.js';
import { lerpPose, poseToModelInput, rotvecToQuaternion, swayMotion } from './pose.js';
import { buildUi, motionFromJson } from './ui.js';

const params = new URLSearchParams(location.search);
const AVATAR = params.get('avatar') || 'avatar/';
const api = (window.uvatar = { ready: false, error: null, stats: { inferenceMs: null, fps: 0, backend: null, precision: null, adapter: null, backendNote: '', inferences: 0 } });

function fail(err) {
  console.error(err);
  api.error = String(err && err.stack ? err.stack : err);
  const box = document.getElementById('error');
  box.textContent = `uvatar viewer: ${err}`;
  box.hidden = false;
}

async function loadMask(url, R) {
  const keep = new Float32Array(R * R).fill(1);
  try {
    const img = new Image();
    img.src = url;
    await img.decode();
    const c = document.createElement('canvas');
    c.width = R; c.height = R;
    const ctx = c.getContext('2d');
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(img, 0, 0, R, R);
    const px = ctx.getImageData(0, 0, R, R).data;
    for (let i = 0; i < R * R; i++) keep[i] = 1 - px[4 * i] / 255;
  } catch (e) {
    console.warn('no finger/toe mask', e);
  }
  return keep;
}

/** Bilinear lookup with clamp-to-edge in an RGBA float image (R x R, row 0 at t = 0), like the GPU. */
function sampleBilinear(data, R, u, t) {
  const x = Math.min(Math.max(u * R - 0.5, 0), R - 1);
  const y = Math.min(Math.max(t * R - 0.5, 0), R - 1);
  const x0 = Math.floor(x), y0 = Math.floor(y);
  const x1 = Math.min(x0 + 1, R - 1), y1 = Math.min(y0 + 1, R - 1);
  const fx = x - x0, fy = y - y0;
  const out = [0, 0, 0];
  for (let c = 0; c < 3; c++) {
    const a = data[4 * (y0 * R + x0) + c] * (1 - fx) + data[4 * (y0 * R + x1) + c] * fx;
    const b = data[4 * (y1 * R + x0) + c] * (1 - fx) + data[4 * (y1 * R + x1) + c] * fx;
    out[c] = a * (1 - fy) + b * fy;
  }
  return out;
}

function toBase64(floats) {
  const bytes = new Uint8Array(floats.buffer, floats.byteOffset, floats.byteLength);
  let s = '';
  for (let i = 0; i < bytes.length; i += 0x8000) s += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  return btoa(s);
}

async function main() {
  const manifest = await (await fetch(AVATAR + 'manifest.json')).json();
  const J = manifest.joint_names.length;
  const R = manifest.texels;

  const canvas = document.getElementById('view');
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: params.get('aa') !== '0', preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
  renderer.setSize(window.innerWidth, window.innerHeight);
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xdfe3e8);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x8a8070, 2.2));
  const sun = new THREE.DirectionalLight(0xffffff, 1.6);
  sun.position.set(1.5, 3, 4);
  scene.add(sun);
  const camera = new THREE.PerspectiveCamera(35, window.innerWidth / window.innerHeight, 0.01, 100);
  const controls = new OrbitControls(camera, canvas);

  const [ort, gltf] = await Promise.all([loadOrt(), new GLTFLoader().loadAsync(AVATAR + manifest.glb)]);
  const generator = await Generator.create(ort, AVATAR, manifest, params.get('ep') || 'auto', params.get('precision') || 'auto');
  Object.assign(api.stats, { backend: generator.backend, precision: generator.precision, adapter: generator.adapter,
                             backendNote: generator.note });

  let mesh = null;
  gltf.scene.traverse((o) => { if (o.isSkinnedMesh && !mesh) mesh = o; });
  if (!mesh) throw new Error(`${manifest.glb}: no skinned mesh`);
  const geom = mesh.geometry;
  geom.setAttribute('dispUv', geom.getAttribute('uv1') || geom.getAttribute('uv'));
  const floatLinear = renderer.extensions.has('OES_texture_float_linear');
  const colorTex = makeColorTexture(R);
  const dispTex = makeDisplacementTexture(R, floatLinear);
  const dispFrame = manifest.displacement.frame === 'rest' ? 'rest' : 'body';
  mesh.material = makeAvatarMaterial(colorTex, dispTex, manifest.displacement.scale ?? 1.0, dispFrame);
  mesh.frustumCulled = false;
  const avatar = new THREE.Group();
  avatar.add(gltf.scene);
  scene.add(avatar);

  const bones = mesh.skeleton.bones;
  const restQuats = bones.map((b) => b.quaternion.clone());
  const keep = await loadMask(AVATAR + manifest.finger_toe_mask, R);

  // frame the camera on the rest-pose bounding box (the avatar faces +Z)
  const box = new THREE.Box3().setFromBufferAttribute(geom.getAttribute('position'));
  const center = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const dist = (1.25 * Math.max(size.y, size.x)) / (2 * Math.tan((camera.fov * Math.PI) / 360));
  camera.position.set(center.x + 0.25 * dist, center.y + 0.1 * size.y, center.z + dist);
  controls.target.copy(center);
  controls.update();
  // the floor under the rest pose's soles, for a motion's root path to be seen against
  const floor = new THREE.GridHelper(20, 40, 0x9aa3ad, 0xc3c9d0);
  floor.position.set(center.x, box.min.y, center.z);
  scene.add(floor);

  const pose = new Float32Array(J * 3);
  const q = new THREE.Quaternion();
  function applyPoseToBones() {
    for (let j = 0; j < J; j++) {
      rotvecToQuaternion(pose[3 * j], pose[3 * j + 1], pose[3 * j + 2], q);
      bones[j].quaternion.copy(restQuats[j]).multiply(q);
    }
  }

  // inference: at most one in flight; the latest pose wins. Driven by pose changes, never by
  // requestAnimationFrame: headless or background pages may stall rAF, and waiters must not hang then.
  let pending = false;
  let busy = false;
  let idleWaiters = [];
  function drawNow() {
    try {
      controls.update();
      renderer.render(scene, camera);
      ui.showStats(api.stats);
    } catch (e) {
      console.error('draw failed', e);
    }
  }
  function settleIdleWaiters() {
    if (busy || pending || !idleWaiters.length) return;
    const waiters = idleWaiters;
    idleWaiters = [];
    drawNow(); // the latest maps are on the canvas (preserveDrawingBuffer) before anyone is told
    waiters.forEach((w) => w());
  }
  async function pump() {
    busy = true;
    try {
      while (pending) {
        pending = false;
        const r = await generator.run(pose.slice());
        uploadMaps(colorTex, dispTex, r.texture, r.displacement, keep);
        api.stats.inferenceMs = r.ms;
        api.stats.inferences += 1;
      }
    } catch (e) {
      fail(e);
    }
    busy = false;
    settleIdleWaiters();
  }
  function poseChanged() {
    applyPoseToBones();
    pending = true;
    if (!busy) pump();
  }
  /** A promise for the next idle moment that rejects after `timeoutMs` with the viewer's state. */
  function whenIdle(timeoutMs = 60000) {
    let timer = null;
    const idle = new Promise((resolve) => { idleWaiters.push(resolve); });
    const limit = new Promise((_, reject) => {
      timer = setTimeout(() => reject(new Error(`uvatar.whenIdle: not idle after ${timeoutMs} ms `
        + `(busy=${busy}, pending=${pending}, inferences=${api.stats.inferences}, error=${api.error})`)), timeoutMs);
    });
    queueMicrotask(settleIdleWaiters); // already idle: resolve without waiting for a frame
    return Promise.race([idle, limit]).finally(() => clearTimeout(timer));
  }

  // motion playback: a timer advances the pose (and so the generator) even when rAF is throttled
  const motions = [swayMotion(manifest)];
  let playing = null;
  let playStart = 0;
  let playTimer = null;
  const scratch = new Float32Array(J * 3);
  let inPlace = false;
  const followed = new THREE.Vector3(); // the camera's shift so far, following the root's path
  /** The avatar's offset at motion frame i + a (metres): the root's path from the first frame (Th[i] - Th[0],
   *  linear between frames; the body poses as V = R(Rh) X + Th), its horizontal part dropped in place. */
  function rootOffset(m, i, a, out) {
    out.set(0, 0, 0);
    if (!m.Th) return out;
    const t0 = m.Th[0], t1 = m.Th[i], t2 = m.Th[(i + 1) % m.Th.length];
    out.set(t1[0] + a * (t2[0] - t1[0]) - t0[0], t1[1] + a * (t2[1] - t1[1]) - t0[1], t1[2] + a * (t2[2] - t1[2]) - t0[2]);
    if (inPlace) { out.x = 0; out.z = 0; }
    return out;
  }
  /** Move the camera and its target with the avatar's horizontal position (the view orbits the walker). */
  function follow() {
    const dx = avatar.position.x - followed.x, dz = avatar.position.z - followed.z;
    camera.position.x += dx; camera.position.z += dz;
    controls.target.x += dx; controls.target.z += dz;
    followed.set(avatar.position.x, 0, avatar.position.z);
  }
  function advanceMotion(now) {
    if (!playing) return;
    const t = ((now - playStart) / 1000) * playing.fps;
    const n = playing.poses.length;
    const i = Math.floor(t) % n;
    lerpPose(playing.poses[i], playing.poses[(i + 1) % n], t - Math.floor(t), scratch);
    pose.set(scratch.subarray(0, pose.length));
    if (playing.Rh) { // global rotation about the model origin; the maps live in the body frame
      const r = playing.Rh[i];
      rotvecToQuaternion(r[0], r[1], r[2], avatar.quaternion);
    }
    rootOffset(playing, i, t - Math.floor(t), avatar.position);
    follow();
    ui.refreshSliders();
    poseChanged();
  }
  function stopMotion() {
    playing = null;
    clearInterval(playTimer);
    playTimer = null;
    avatar.quaternion.identity();
    avatar.position.set(0, 0, 0);
    follow();
  }
  function playMotion(m) {
    stopMotion();
    if (!m || !m.poses || !m.poses.length) { console.warn('not a motion', m); return; }
    playing = m;
    playStart = performance.now();
    playTimer = setInterval(() => {
      try { advanceMotion(performance.now()); } catch (e) { console.error('motion step failed', e); stopMotion(); }
    }, 1000 / Math.min(60, m.fps || 30));
  }

  const ui = buildUi({ manifest, pose, motions, onPose: poseChanged, onPlay: playMotion,
    onStop: stopMotion, onMotionLoaded: (m) => { motions.push(m); playMotion(m); },
    onInPlace: (on) => { inPlace = on; } });
  try {
    const list = await (await fetch('api/motions')).json();
    for (const entry of list) ui.addMotionEntry(entry);
  } catch (e) {
    console.warn('no motion list', e);
  }

  let frames = 0;
  let fpsStart = performance.now();
  function frame(now) {
    try {
      controls.update();
      renderer.render(scene, camera);
      frames += 1;
      if (now - fpsStart > 1000) {
        api.stats.fps = (1000 * frames) / (now - fpsStart);
        frames = 0;
        fpsStart = now;
      }
      ui.showStats(api.stats);
    } catch (e) {
      console.error('frame failed', e); // keep the loop alive: one bad frame must not freeze the page
    } finally {
      requestAnimationFrame(frame);
    }
  }

  window.addEventListener('resize', () => {
    camera.aspect = window.innerWidth / window.innerHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(window.innerWidth, window.innerHeight);
  });

  Object.assign(api, {
    manifest,
    getPose: () => Array.from(pose),
    /** World positions (J x [x, y, z]) of the skeleton's joints as currently posed (metres). */
    jointWorldPositions() {
      avatar.updateMatrixWorld(true);
      const v = new THREE.Vector3();
      return bones.map((b) => b.getWorldPosition(v).toArray());
    },
    setPose(values) { pose.set(values); ui.refreshSliders(); poseChanged(); },
    setJointAngle(joint, axis, value) { pose[3 * joint + axis] = value; ui.refreshSliders(); poseChanged(); },
    playMotion: (index) => playMotion(motions[index ?? 0]),
    /** Add a motion ({name, fps, poses: [[J*3]], Rh?: [[3]], Th?: [[3]] metres}, as api/motions serves) and play it. */
    playMotionJson(body) { const m = motionFromJson(body, body.name || 'motion'); motions.push(m); playMotion(m); },
    /** The avatar group's offset (metres): the playing motion's root path from its first frame. */
    avatarOffset: () => avatar.position.toArray(),
    /** The orbit camera's target (metres): it follows the avatar's horizontal path while a motion plays. */
    cameraTarget: () => controls.target.toArray(),
    /** Multiply the displacement (1 = as exported, 0 = bare skinned body); for inspection and tests. */
    setDisplacementScale(s) { mesh.material.userData.uniforms.uDisplacementScale.value = s; },
    stop: stopMotion,
    /** True while a motion plays. */
    isPlaying: () => playing !== null,
    /**
     * Resolves once no inference is pending and the latest maps have been drawn; rejects with the
     * viewer's state after `timeoutMs` (default 60 s). Does not depend on requestAnimationFrame.
     */
    whenIdle,
    /**
     * CPU twin of the vertex shader for the given vertex indices, model space, metres: rest frame
     * skin(p_rest + scale * D) (SkinnedMesh.applyBoneTransform); body frame skin(p_rest) + scale * D,
     * with D = bilinear(displacement map, dispUv).
     */
    displacedVertices(indices) {
      avatar.updateMatrixWorld(true);
      const uvs = geom.getAttribute('dispUv');
      const scale = mesh.material.userData.uniforms.uDisplacementScale.value;
      const v = new THREE.Vector3();
      const pos = geom.getAttribute('position');
      return indices.map((i) => {
        const d = sampleBilinear(dispTex.image.data, R, uvs.getX(i), uvs.getY(i));
        if (dispFrame === 'rest') { // displace the rest vertex, then skin (as the vertex shader does)
          v.fromBufferAttribute(pos, i).add(new THREE.Vector3(scale * d[0], scale * d[1], scale * d[2]));
          mesh.applyBoneTransform(i, v);
          return [v.x, v.y, v.z];
        }
        mesh.getVertexPosition(i, v);
        return [v.x + scale * d[0], v.y + scale * d[1], v.z + scale * d[2]];
      });
    },
    /** The generator input for a full pose under `encoding` (default: the manifest's); for parity tests. */
    encodePose: (values, encoding) => Array.from(poseToModelInput(values, encoding || manifest.pose_encoding)),
    /** Run the generator for `values` (J*3) without touching the view; float32 outputs as base64. */
    async runGenerator(values) {
      const r = await generator.run(Float32Array.from(values));
      return { texture: toBase64(r.texture), displacement: toBase64(r.displacement), dims: r.dims, ms: r.ms };
    },
    /** Mean/median inference ms over n random poses (after one warm-up). */
    async benchmark(n = 10) {
      const p = new Float32Array(J * 3);
      await generator.run(p);
      const times = [];
      for (let i = 0; i < n; i++) {
        for (let k = 0; k < p.length; k++) p[k] = (Math.random() - 0.5) * 0.6;
        times.push((await generator.run(p)).ms);
      }
      times.sort((a, b) => a - b);
      return { mean_ms: times.reduce((a, b) => a + b, 0) / n, median_ms: times[n >> 1], min_ms: times[0], n, backend: generator.backend, precision: generator.precision };
    },
  });

  poseChanged();
  requestAnimationFrame(frame);
  await whenIdle(300000); // the first inference compiles the model: generous under load
  if (params.get('play') !== null) playMotion(motions[Number(params.get('play')) || 0]);
  api.ready = true;
  document.body.dataset.ready = '1';
}

main().catch(fail);
