// The job's training cameras (output/cameras.json, written by pipeline/export/cameras.py): small frustums in the
// scene and the viewer's starting pose. Camera axes in that file are OpenCV's (x right, y down, z forward) in the
// PLY's world frame; three.js cameras look down -z with y up, hence the sign flips below.
import * as THREE from "three";

const FRUSTUM_COLOUR = 0xffa040;

/** Line segments drawing each camera as a pyramid (apex at the centre, the image rectangle at `size`). */
export function cameraFrustums(cameras, size) {
  const pts = [];
  for (const c of cameras) {
    const R = c.rotation; // world_from_cam, rows
    const C = new THREE.Vector3(...c.position);
    const hx = Math.tan((c.fov_x_deg * Math.PI) / 360) * size;
    const hy = Math.tan((c.fov_y_deg * Math.PI) / 360) * size;
    const corner = (sx, sy) => {
      const x = sx * hx, y = sy * hy, z = size; // camera frame (OpenCV)
      return new THREE.Vector3(
        C.x + R[0][0] * x + R[0][1] * y + R[0][2] * z,
        C.y + R[1][0] * x + R[1][1] * y + R[1][2] * z,
        C.z + R[2][0] * x + R[2][1] * y + R[2][2] * z,
      );
    };
    const k = [corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, 1)];
    for (let i = 0; i < 4; i++) pts.push(C, k[i], k[i], k[(i + 1) % 4]);
    // a tick above the image's top edge shows which way is up in the photo
    const top = corner(0, -1.4);
    pts.push(k[0], top, top, k[1]);
  }
  const geom = new THREE.BufferGeometry().setFromPoints(pts);
  const lines = new THREE.LineSegments(geom, new THREE.LineBasicMaterial({ color: FRUSTUM_COLOUR }));
  lines.name = "cameras";
  return lines;
}

/** Median distance from a camera to its nearest neighbour (frustums this size do not overlap); Infinity for one. */
function medianSpacing(cameras) {
  const step = Math.max(1, Math.floor(cameras.length / 400)); // O(n²): a few hundred cameras at most
  const c = cameras.filter((_, i) => i % step === 0).map((x) => new THREE.Vector3(...x.position));
  if (c.length < 2) return Infinity;
  const nearest = c.map((p, i) => Math.min(...c.filter((_, j) => j !== i).map((q) => p.distanceTo(q))));
  nearest.sort((a, b) => a - b);
  return nearest[Math.floor(nearest.length / 2)];
}

/**
 * Where the viewer starts: on the first camera (by name) looking where it looked, at the median depth of the
 * Gaussians it saw, upright along the cameras' mean image-up; without cameras, in front of the bounding box.
 */
export function startPose(cams, box) {
  const size = box.isEmpty() ? 1 : box.getSize(new THREE.Vector3()).length();
  const centre = box.isEmpty() ? new THREE.Vector3() : box.getCenter(new THREE.Vector3());
  const list = cams && cams.cameras ? [...cams.cameras].sort((a, b) => (a.name < b.name ? -1 : 1)) : [];
  if (!list.length) {
    const up = new THREE.Vector3(0, -1, 0); // COLMAP worlds are usually y-down
    return {
      position: centre.clone().add(new THREE.Vector3(0, 0, -size)),
      target: centre,
      up,
      fovY: 50,
      near: size * 1e-3,
      far: size * 100,
      markerSize: size * 0.03,
    };
  }
  const up = new THREE.Vector3();
  for (const c of list) up.add(new THREE.Vector3(-c.rotation[0][1], -c.rotation[1][1], -c.rotation[2][1]));
  if (up.lengthSq() < 1e-12) up.set(0, -1, 0);
  up.normalize();
  const c0 = list[0];
  const position = new THREE.Vector3(...c0.position);
  const forward = new THREE.Vector3(c0.rotation[0][2], c0.rotation[1][2], c0.rotation[2][2]).normalize();
  let depth = c0.median_depth;
  if (!(depth > 0)) depth = Math.max(centre.clone().sub(position).dot(forward), size * 0.1);
  const spread = cams.extent > 0 ? cams.extent : size;
  return {
    position,
    target: position.clone().addScaledVector(forward, depth),
    up,
    fovY: c0.fov_y_deg,
    near: depth * 1e-3,
    far: Math.max(depth, spread, size) * 100,
    markerSize: Math.max(Math.min(depth * 0.15, 0.6 * medianSpacing(list)), depth * 0.02),
  };
}
