// The avatar material: MeshStandardMaterial + a displacement applied in the vertex shader.
//
// Displacement D (metres, RGB = x, y, z) is sampled at the canonical UV `dispUv` (glTF TEXCOORD_1:
// all seam copies of a vertex share it, so the surface does not crack). Where it is added depends on
// the frame the generator was trained in (manifest displacement.frame):
//   "rest": BEFORE skinning, so the bones rotate it:      p = skinned(p_rest + scale * D(dispUv))
//   "body": AFTER skinning, in the skinned mesh's model space (world axes of the posed body with the
//           root at rest):                                 p = skinned(p_rest) + scale * D(dispUv)
// Normals come from the displaced surface: flatShading makes three.js take the normal from screen-space
// derivatives of the displaced view position in the fragment shader.
import * as THREE from 'three';

export function makeDisplacementTexture(R, floatLinear) {
  const tex = new THREE.DataTexture(new Float32Array(R * R * 4), R, R, THREE.RGBAFormat, THREE.FloatType);
  tex.minFilter = tex.magFilter = floatLinear ? THREE.LinearFilter : THREE.NearestFilter;
  tex.generateMipmaps = false;
  tex.flipY = false; // row 0 of the data is glTF v = 0 (the map's v-up row 0 is v = 1: same row)
  tex.needsUpdate = true;
  return tex;
}

export function makeColorTexture(R) {
  const tex = new THREE.DataTexture(new Uint8Array(R * R * 4), R, R, THREE.RGBAFormat, THREE.UnsignedByteType);
  tex.colorSpace = THREE.SRGBColorSpace;
  tex.minFilter = THREE.LinearMipmapLinearFilter;
  tex.magFilter = THREE.LinearFilter;
  tex.generateMipmaps = true;
  tex.flipY = false;
  tex.needsUpdate = true;
  return tex;
}

export function makeAvatarMaterial(colorTexture, displacementTexture, scale, frame = 'body') {
  const material = new THREE.MeshStandardMaterial({
    map: colorTexture, roughness: 0.85, metalness: 0.0, flatShading: true,
  });
  material.userData.uniforms = {
    uDisplacementMap: { value: displacementTexture },
    uDisplacementScale: { value: scale },
  };
  const displace = 'transformed += uDisplacementScale * textureLod(uDisplacementMap, dispUv, 0.0).xyz;';
  material.onBeforeCompile = (shader) => {
    Object.assign(shader.uniforms, material.userData.uniforms);
    shader.vertexShader = shader.vertexShader
      .replace('#include <common>', `#include <common>
attribute vec2 dispUv;
uniform sampler2D uDisplacementMap;
uniform float uDisplacementScale;`)
      .replace('#include <skinning_vertex>', frame === 'rest'
        ? `${displace}
#include <skinning_vertex>`
        : `#include <skinning_vertex>
${displace}`);
  };
  material.customProgramCacheKey = () => `uvatar-displaced-${frame}`;
  return material;
}

/**
 * Upload generator outputs (NCHW float32, batch 0) into the textures.
 * texture (3, R, R) in [0, 1] -> sRGB bytes; displacement (3, R, R) metres, multiplied by (1 - mask).
 */
export function uploadMaps(colorTexture, displacementTexture, texture, displacement, keep) {
  const R = colorTexture.image.width;
  const n = R * R;
  const rgba = colorTexture.image.data;
  const disp = displacementTexture.image.data;
  for (let i = 0; i < n; i++) {
    rgba[4 * i] = Math.round(Math.min(Math.max(texture[i], 0), 1) * 255);
    rgba[4 * i + 1] = Math.round(Math.min(Math.max(texture[n + i], 0), 1) * 255);
    rgba[4 * i + 2] = Math.round(Math.min(Math.max(texture[2 * n + i], 0), 1) * 255);
    rgba[4 * i + 3] = 255;
    const k = keep ? keep[i] : 1;
    disp[4 * i] = displacement[i] * k;
    disp[4 * i + 1] = displacement[n + i] * k;
    disp[4 * i + 2] = displacement[2 * n + i] * k;
    disp[4 * i + 3] = 0;
  }
  colorTexture.needsUpdate = true;
  displacementTexture.needsUpdate = true;
}
