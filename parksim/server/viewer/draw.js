// Arrays of the render reply onto canvases: uint8 RGB images as they are, float32 depth through a colour map.

export const DEPTH_RANGE_M = [0.5, 30];

// Turbo colour map (Mikhailov's polynomial fit), 256 RGB entries: dark blue (far) .. dark red (near).
const TURBO = (() => {
  const poly = (t, c) => c.reduceRight((acc, k) => acc * t + k, 0);
  const R = [0.13572138, 4.6153926, -42.66032258, 132.13108234, -152.94239396, 59.28637943];
  const G = [0.09140261, 2.19418839, 4.84296658, -14.18503333, 4.27729857, 2.82956604];
  const B = [0.1066733, 12.64194608, -60.58204836, 110.36276771, -89.90310912, 27.34824973];
  const lut = new Uint8ClampedArray(256 * 3);
  for (let i = 0; i < 256; i++) {
    const t = i / 255;
    lut.set([poly(t, R), poly(t, G), poly(t, B)].map((v) => Math.round(255 * v)), 3 * i);
  }
  return lut;
})();

function sized(canvas, width, height) {
  if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
  return canvas.getContext("2d");
}

// uint8 [H, W, 3] -> canvas pixels.
export function drawRGB(canvas, { shape: [h, w], data }) {
  const ctx = sized(canvas, w, h);
  const out = ctx.createImageData(w, h);
  for (let i = 0, j = 0; i < w * h; i++, j += 3) {
    out.data[4 * i] = data[j]; out.data[4 * i + 1] = data[j + 1]; out.data[4 * i + 2] = data[j + 2];
    out.data[4 * i + 3] = 255;
  }
  ctx.putImageData(out, 0, 0);
}

// Colour index 0..255 of a depth (m) on a log scale over DEPTH_RANGE_M, near = 255 (red); -1 where nothing was hit.
function depthIndex(d) {
  if (!(d > 0)) return -1;
  const [near, far] = DEPTH_RANGE_M;
  const t = (Math.log(far) - Math.log(Math.min(Math.max(d, near), far))) / (Math.log(far) - Math.log(near));
  return Math.round(255 * t);
}

// float32 [H, W] depth (m, 0 = no surface) -> turbo-coloured canvas pixels, black where nothing was hit.
export function drawDepth(canvas, { shape: [h, w], data }) {
  const ctx = sized(canvas, w, h);
  const out = ctx.createImageData(w, h);
  for (let i = 0; i < w * h; i++) {
    const k = depthIndex(data[i]);
    if (k >= 0) out.data.set(TURBO.subarray(3 * k, 3 * k + 3), 4 * i);
    out.data[4 * i + 3] = 255;
  }
  ctx.putImageData(out, 0, 0);
}

// A horizontal legend of the depth colours, near on the left.
export function drawDepthLegend(canvas) {
  const ctx = sized(canvas, 256, 1);
  const out = ctx.createImageData(256, 1);
  for (let i = 0; i < 256; i++) {
    out.data.set(TURBO.subarray(3 * (255 - i), 3 * (255 - i) + 3), 4 * i);
    out.data[4 * i + 3] = 255;
  }
  ctx.putImageData(out, 0, 0);
}
