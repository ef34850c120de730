// The viewer's on-screen panel: stats counter, joint sliders, motion playback and BVH drop.
const AXES = ['x', 'y', 'z'];

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  Object.assign(e, attrs);
  for (const c of children) e.append(c);
  return e;
}

export function buildUi({ manifest, pose, motions, onPose, onPlay, onStop, onMotionLoaded, onInPlace }) {
  const panel = document.getElementById('panel');
  const stats = el('div', { id: 'stats', textContent: 'loading…' });
  const jointSelect = el('select', { id: 'joint-select' });
  manifest.joint_names.forEach((name, j) => jointSelect.append(el('option', { value: String(j), textContent: `${j} ${name}` })));
  const cond = new Set(manifest.pose_encoding.joints);
  const firstCond = manifest.pose_encoding.joints.find((j) => manifest.joint_parents[j] >= 0);
  jointSelect.value = String(firstCond ?? 0);

  const sliders = AXES.map((axis, c) => {
    const input = el('input', { id: `slider-${axis}`, type: 'range', min: String(-Math.PI), max: String(Math.PI), step: '0.01', value: '0' });
    const label = el('span', { className: 'value' });
    input.addEventListener('input', () => {
      pose[3 * Number(jointSelect.value) + c] = Number(input.value);
      label.textContent = Number(input.value).toFixed(2);
      onStop();
      onPose();
    });
    return { input, label, row: el('label', { className: 'slider' }, `${axis} `, input, label) };
  });
  const refreshSliders = () => {
    const j = Number(jointSelect.value);
    sliders.forEach((s, c) => { s.input.value = String(pose[3 * j + c]); s.label.textContent = pose[3 * j + c].toFixed(2); });
    jointSelect.title = cond.has(j) ? 'conditions the generator' : 'skeleton only (not a conditioning joint)';
  };
  jointSelect.addEventListener('change', refreshSliders);

  const motionSelect = el('select', { id: 'motion-select' });
  motions.forEach((m, i) => motionSelect.append(el('option', { value: String(i), textContent: m.name })));
  const play = el('button', { id: 'play', textContent: '▶ play' });
  const stop = el('button', { id: 'stop', textContent: '■ stop' });
  const reset = el('button', { id: 'reset', textContent: 'rest pose' });
  play.onclick = async () => {
    const opt = motionSelect.selectedOptions[0];
    if (opt && opt.dataset.url && !opt.dataset.loaded) {
      drop.textContent = `loading ${opt.textContent}…`;
      let m;
      try {
        m = await loadMotionJson(opt.dataset.url, opt.textContent);
      } catch (err) {
        drop.textContent = `could not load ${opt.textContent}: ${err.message}`;
        return;
      }
      drop.textContent = `playing ${m.name} (${m.poses.length} frames)`;
      motions.push(m);
      opt.value = String(motions.length - 1);
      opt.dataset.loaded = '1';
    }
    onPlay(motions[Number(motionSelect.value)]);
  };
  stop.onclick = onStop;
  // a motion's root path (Th): walked over the floor, the camera following; "in place" keeps only its height
  const inPlace = el('input', { id: 'in-place', type: 'checkbox' });
  inPlace.addEventListener('change', () => onInPlace(inPlace.checked));
  reset.onclick = () => { onStop(); pose.fill(0); refreshSliders(); onPose(); };

  const drop = el('div', { id: 'drop', textContent: 'drop a .bvh file anywhere to retarget and play it' });
  panel.append(stats, el('div', { className: 'row' }, 'joint ', jointSelect), ...sliders.map((s) => s.row),
    el('div', { className: 'row' }, motionSelect, play, stop, reset),
    el('label', { className: 'row', title: 'play the motion without its horizontal root path' }, inPlace, ' in place'), drop);

  window.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('hover'); });
  window.addEventListener('dragleave', () => drop.classList.remove('hover'));
  window.addEventListener('drop', async (e) => {
    e.preventDefault();
    drop.classList.remove('hover');
    const file = e.dataTransfer.files[0];
    if (!file) return;
    drop.textContent = `retargeting ${file.name}…`;
    try {
      const res = await fetch('api/retarget', { method: 'POST', body: await file.text(), headers: { 'X-Filename': file.name } });
      const body = await res.json();
      if (!res.ok) throw new Error(body.error || res.statusText);
      const m = motionFromJson(body, file.name);
      motionSelect.append(el('option', { value: String(motions.length), textContent: m.name }));
      motionSelect.value = String(motions.length);
      onMotionLoaded(m);
      drop.textContent = `playing ${file.name} (${m.poses.length} frames)`;
    } catch (err) {
      drop.textContent = `could not use ${file.name}: ${err.message}`;
    }
  });

  refreshSliders();
  return {
    refreshSliders,
    addMotionEntry(entry) {
      const opt = el('option', { value: '', textContent: entry.name });
      opt.dataset.url = entry.url;
      motionSelect.append(opt);
    },
    showStats(s) {
      const ms = s.inferenceMs == null ? '–' : s.inferenceMs.toFixed(1);
      const where = s.backend === 'webgpu' ? `WebGPU ${s.precision} (${s.adapter})` : `wasm ${s.precision}`;
      const why = s.backendNote ? ` (${s.backendNote})` : '';
      stats.textContent = `inference ${ms} ms · ${s.fps.toFixed(0)} fps · ${where}${why} · ${manifest.texels}²`;
    },
  };
}

export function motionFromJson(body, name) {
  const J3 = body.poses[0].length;
  return {
    name: body.name || name, fps: body.fps || 30, poses: body.poses.map((p) => Float32Array.from(p.slice(0, J3))),
    Rh: body.Rh ? body.Rh.map((r) => Float32Array.from(r)) : null,
    Th: body.Th ? body.Th.map((t) => Float32Array.from(t)) : null, // metres, the root's path
  };
}

async function loadMotionJson(url, name) {
  const res = await fetch(url);
  if (!res.ok) throw new Error(`${url}: HTTP ${res.status}`);
  return motionFromJson(await res.json(), name);
}
