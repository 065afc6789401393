// Where the viewer may go in a scene (GET /scenes/{id}): start pose, the server's pose limits, recorded coverage.

// Views stay sharp this close (m) to the recorded path: farther, the cameras see surfaces from angles
// no recorded frame saw, and the reconstruction smears.
export const COVERAGE_M = 3.0;

// The pose the viewer opens at: the middle of the recorded path (its surroundings were seen from both
// sides), else the first lane 30 % along the scene.
export function startPose(info) {
  const path = info.recorded_path;
  if (path && path.length) {
    const [x, y, yaw] = path[Math.floor((path.length - 1) / 2)];
    return { x, y, yaw };
  }
  const lanes = info.map && info.map.garage && info.map.garage.lanes;
  const [x0, x1] = info.bounds.x;
  const [y0, y1] = info.bounds.y;
  return { x: x0 + 0.3 * (x1 - x0), y: lanes && lanes.length ? lanes[0] : (y0 + y1) / 2, yaw: 0 };
}

// The x and y range the server renders: the scene bounds grown by its pose margin.
export function poseLimits(info) {
  const m = info.pose_margin_m;
  return { x: [info.bounds.x[0] - m, info.bounds.x[1] + m], y: [info.bounds.y[0] - m, info.bounds.y[1] + m] };
}

// ``pose`` with x and y held inside ``poseLimits``; ``clamped`` tells whether it had to move.
export function clampPose(info, pose) {
  const lim = poseLimits(info);
  const x = Math.min(Math.max(pose.x, lim.x[0]), lim.x[1]);
  const y = Math.min(Math.max(pose.y, lim.y[0]), lim.y[1]);
  return { pose: { ...pose, x, y }, clamped: x !== pose.x || y !== pose.y };
}

function segmentDistance(px, py, [ax, ay], [bx, by]) {
  const dx = bx - ax, dy = by - ay;
  const len2 = dx * dx + dy * dy;
  const t = len2 > 0 ? Math.min(1, Math.max(0, ((px - ax) * dx + (py - ay) * dy) / len2)) : 0;
  return Math.hypot(px - ax - t * dx, py - ay - t * dy);
}

// Distance (m) from (x, y) to the recorded path polyline.
export function pathDistance(path, x, y) {
  if (path.length === 1) return Math.hypot(x - path[0][0], y - path[0][1]);
  let best = Infinity;
  for (let i = 1; i < path.length; i++) best = Math.min(best, segmentDistance(x, y, path[i - 1], path[i]));
  return best;
}

// { covered, distance, text }: whether views at ``pose`` come from the recorded area, and a warning when not.
export function coverage(info, pose) {
  const path = info.recorded_path;
  if (path && path.length) {
    const distance = pathDistance(path, pose.x, pose.y);
    const covered = distance <= COVERAGE_M;
    return { covered, distance, text: covered ? "" : `Off the recorded path: ${distance.toFixed(1)} m from where ` +
      `the cameras drove (views are sharp within ${COVERAGE_M} m); expect smeared views here.` };
  }
  const inside = ["x", "y"].every((a) => info.bounds[a][0] <= pose[a] && pose[a] <= info.bounds[a][1]);
  return { covered: inside, distance: null,
           text: inside ? "" : "Outside the scene bounds (this scene has no recorded path): expect smeared views." };
}
