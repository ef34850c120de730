// Pose utilities shared by the viewer and its tests.
// A pose is a Float32Array of J*3 local axis-angle components (radians) in the body model's joint
// order, exactly the `poses` of an EasyMocap fit (root rotation zero).
import * as THREE from 'three';

/**
 * Full pose (J*3) -> generator input, as manifest.pose_encoding says (twin of
 * uvatar.avh.exporters.engine.pose_to_model_input).
 * type "angles": the 3*J_c angles of the conditioning joints (the model encodes sin/cos itself);
 * type "sincos": [sin a0, cos a0, sin a1, cos a1, ...].
 */
export function poseToModelInput(pose, encoding) {
  const joints = encoding.joints;
  const sincos = encoding.type === 'sincos';
  const out = new Float32Array(joints.length * 3 * (sincos ? 2 : 1));
  let k = 0;
  for (const j of joints) {
    for (let c = 0; c < 3; c++) {
      const a = pose[3 * j + c];
      if (sincos) { out[k++] = Math.sin(a); out[k++] = Math.cos(a); } else { out[k++] = a; }
    }
  }
  return out;
}

const _axis = new THREE.Vector3();
/** Axis-angle (x, y, z) radians -> THREE.Quaternion (written into `target`). */
export function rotvecToQuaternion(x, y, z, target) {
  const angle = Math.hypot(x, y, z);
  if (angle < 1e-12) return target.set(0, 0, 0, 1);
  _axis.set(x / angle, y / angle, z / angle);
  return target.setFromAxisAngle(_axis, angle);
}

/** Linear interpolation between two poses (per component; fine for the small steps of playback). */
export function lerpPose(a, b, t, out) {
  for (let i = 0; i < out.length; i++) out[i] = a[i] + (b[i] - a[i]) * t;
  return out;
}

/** A built-in motion that needs no file: a gentle sway of the spine, arms and head. */
export function swayMotion(manifest, frames = 96) {
  const J = manifest.joint_names.length;
  const s = manifest.semantic_joints || {};
  const poses = [];
  for (let f = 0; f < frames; f++) {
    const t = (2 * Math.PI * f) / frames;
    const p = new Float32Array(J * 3);
    const add = (name, c, v) => { if (name in s) p[3 * s[name] + c] += v; };
    add('spine1', 1, 0.25 * Math.sin(t));
    add('spine2', 2, 0.1 * Math.sin(t));
    add('neck', 1, 0.3 * Math.sin(2 * t));
    add('head', 0, 0.15 * Math.sin(t));
    add('l_shoulder', 2, 0.5 + 0.4 * Math.sin(t));
    add('r_shoulder', 2, -0.5 - 0.4 * Math.sin(t));
    add('l_elbow', 1, 0.6 + 0.5 * Math.sin(t));
    add('r_elbow', 1, -0.6 - 0.5 * Math.sin(t));
    add('l_hip', 0, -0.3 * Math.sin(t));
    add('r_hip', 0, 0.3 * Math.sin(t));
    add('l_knee', 0, 0.3 + 0.3 * Math.sin(t));
    add('r_knee', 0, 0.3 - 0.3 * Math.sin(t));
    if (!Object.keys(s).length) for (let j = 1; j < J; j++) p[3 * j + 2] = 0.3 * Math.sin(t + j);
    poses.push(p);
  }
  return { name: 'sway (built-in)', fps: 30, poses };
}
