// Top-down map of a scene: the area the server renders, the scene bounds, obstacles, slots, the recorded path
// with its covered band, and the ego footprint. World x points right, y up.

import { COVERAGE_M, poseLimits } from "./scene.js";

const WIDTH_PX = 480;
export const COLORS = { outside: "#15171a", floor: "#33373d", band: "rgba(80, 160, 255, 0.18)", path: "#4da3ff",
                        obstacle: "#6b6f76", car: "#8a5a5a", free: "#9be39b", occupied: "rgba(230, 110, 110, 0.45)",
                        ego: "#ffd23f", egoOff: "#ff6a3d" };

export class Minimap {
  constructor(canvas, info) {
    this.canvas = canvas;
    this.info = info;
    this.limits = poseLimits(info);
    const [x0, x1] = this.limits.x, [y0, y1] = this.limits.y;
    this.pxPerM = WIDTH_PX / (x1 - x0);
    canvas.width = WIDTH_PX;
    canvas.height = Math.round((y1 - y0) * this.pxPerM);
  }

  // World (m) -> canvas pixel.
  toCanvas(x, y) {
    return [(x - this.limits.x[0]) * this.pxPerM, (this.limits.y[1] - y) * this.pxPerM];
  }

  // A mouse event's position -> world (m).
  toWorld(ev) {
    const r = this.canvas.getBoundingClientRect();
    const u = (ev.clientX - r.left) * this.canvas.width / r.width, v = (ev.clientY - r.top) * this.canvas.height / r.height;
    return [this.limits.x[0] + u / this.pxPerM, this.limits.y[1] - v / this.pxPerM];
  }

  polygon(ctx, points) {
    ctx.beginPath();
    points.forEach(([x, y], i) => ctx[i ? "lineTo" : "moveTo"](...this.toCanvas(x, y)));
    ctx.closePath();
  }

  // Corners of a rectangle [x_min, x_max, y_min, y_max] in a frame at (x, y, yaw).
  static box(x, y, yaw, [a0, a1, b0, b1]) {
    const c = Math.cos(yaw), s = Math.sin(yaw);
    return [[a0, b0], [a1, b0], [a1, b1], [a0, b1]].map(([a, b]) => [x + c * a - s * b, y + s * a + c * b]);
  }

  drawMap(ctx) {
    const { bounds, map } = this.info;
    ctx.fillStyle = COLORS.outside;
    ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    ctx.fillStyle = COLORS.floor;
    this.polygon(ctx, Minimap.box(0, 0, 0, [...bounds.x, ...bounds.y]));
    ctx.fill();
    for (const o of (map && map.obstacles) || []) {
      const [l, w] = o.size;
      ctx.fillStyle = o.kind === "car" ? COLORS.car : COLORS.obstacle;
      this.polygon(ctx, Minimap.box(o.center[0], o.center[1], o.yaw, [-l / 2, l / 2, -w / 2, w / 2]));
      ctx.fill();
    }
    for (const slot of (map && map.slots) || []) {
      this.polygon(ctx, slot.corners);
      if (slot.occupied) { ctx.fillStyle = COLORS.occupied; ctx.fill(); }
      ctx.strokeStyle = COLORS.free;
      ctx.lineWidth = 1;
      ctx.stroke();
    }
  }

  drawPath(ctx) {
    const path = this.info.recorded_path;
    if (!path || !path.length) return;
    const line = () => {
      ctx.beginPath();
      path.forEach(([x, y], i) => ctx[i ? "lineTo" : "moveTo"](...this.toCanvas(x, y)));
      if (path.length === 1) ctx.lineTo(...this.toCanvas(path[0][0] + 1e-3, path[0][1]));
    };
    ctx.lineCap = ctx.lineJoin = "round";
    line();
    ctx.strokeStyle = COLORS.band;
    ctx.lineWidth = 2 * COVERAGE_M * this.pxPerM;
    ctx.stroke();
    line();
    ctx.strokeStyle = COLORS.path;
    ctx.lineWidth = 2;
    ctx.stroke();
  }

  drawEgo(ctx, pose, covered) {
    const [x0, x1, y0, y1] = this.info.footprint;
    ctx.fillStyle = covered ? COLORS.ego : COLORS.egoOff;
    this.polygon(ctx, Minimap.box(pose.x, pose.y, pose.yaw, this.info.footprint));
    ctx.fill();
    ctx.fillStyle = COLORS.outside;
    this.polygon(ctx, Minimap.box(pose.x, pose.y, pose.yaw, [x1 - 0.25 * (x1 - x0), x1, y0 / 2, y1 / 2]));
    ctx.fill();
  }

  // Redraw everything for the ego at ``pose``; ``covered`` picks the ego's colour.
  draw(pose, covered) {
    const ctx = this.canvas.getContext("2d");
    this.drawMap(ctx);
    this.drawPath(ctx);
    this.drawEgo(ctx, pose, covered);
  }
}
