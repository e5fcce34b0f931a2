// Per-splat colour as shown: the restored scene (the PLY's colours), or the scene seen through the job's
// homogeneous water, I = J·exp(−β_D·r) + B∞·(1 − exp(−β_B·r)) (the paper's eq. 3 with eq. 6), r the distance
// from the viewer's camera to each Gaussian's centre; and the sRGB encoding when the job's physics ran in linear
// light. Both are applied to each Gaussian's colour before Spark blends them (a pixel's blend of encoded or
// watered colours, where the trainer encodes or waters the blended pixel: close where one Gaussian dominates a
// pixel, and what a per-pixel pass would need a depth buffer Spark does not write for).
import * as THREE from "three";
import { dyno } from "@sparkjsdev/spark";

const {
  Gsplat, dynoBlock, splitGsplat, combineGsplat, dynoVec3, dynoFloat, dynoConst,
  add, sub, mul, exp, neg, length, mix, pow, max,
} = dyno;

const SRGB_GAMMA = 1 / 2.2; // the sRGB curve as a power: within 0.01 of the piecewise curve above 0.02

/**
 * Install the colour modifier on `mesh`. `display` is cameras.json's `display` ({colour_space, water}). Returns
 * a setter `setWater(on)` (or null when the job has no medium).
 */
export function installDisplay(mesh, display) {
  const water = display && display.water;
  const linear = display && display.colour_space === "linear";
  if (!water && !linear) return null;
  const on = dynoFloat(0);
  const betaD = dynoVec3(new THREE.Vector3(...(water ? water.beta_D : [0, 0, 0])));
  const betaB = dynoVec3(new THREE.Vector3(...(water ? water.beta_B : [0, 0, 0])));
  const bInf = dynoVec3(new THREE.Vector3(...(water ? water.B_inf : [0, 0, 0])));
  const one = dynoConst("vec3", new THREE.Vector3(1, 1, 1));
  mesh.enableWorldToView = true; // re-run when the camera moves: r depends on it
  mesh.worldModifier = dynoBlock({ gsplat: Gsplat }, { gsplat: Gsplat }, ({ gsplat }) => {
    const { center, rgb } = splitGsplat(gsplat).outputs;
    const r = length(mesh.context.worldToView.apply(center));
    const attenuation = exp(neg(mul(betaD, r)));
    const backscatter = mul(bInf, sub(one, exp(neg(mul(betaB, r)))));
    let colour = mix(rgb, add(mul(rgb, attenuation), backscatter), on);
    if (linear) colour = pow(max(colour, dynoConst("vec3", new THREE.Vector3(0, 0, 0))),
      dynoConst("vec3", new THREE.Vector3(SRGB_GAMMA, SRGB_GAMMA, SRGB_GAMMA)));
    return { gsplat: combineGsplat({ gsplat, rgb: colour }) };
  });
  mesh.updateGenerator();
  if (!water) return null;
  return (flag) => {
    on.value = flag ? 1 : 0;
    mesh.updateVersion();
  };
}

/** The clear colour: the veiling light B∞ with the water on (what infinite depth looks like), else dark. */
export function backgroundColour(display, withWater) {
  const water = display && display.water;
  if (!withWater || !water) return new THREE.Color(0x101820);
  const enc = display.colour_space === "linear" ? (v) => Math.pow(Math.max(v, 0), SRGB_GAMMA) : (v) => v;
  const [r, g, b] = water.B_inf.map((v) => Math.min(Math.max(enc(v), 0), 1));
  return new THREE.Color().setRGB(r, g, b, THREE.SRGBColorSpace);
}
