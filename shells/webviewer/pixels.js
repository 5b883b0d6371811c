// The drawing buffer of a WebGL context as RGB rows, top row first, base64 (for scripts: the
// tests and bench/ compare it with the Python renderer's image).
export function pixels(gl) {
  const w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
  const rgba = new Uint8Array(w * h * 4);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, rgba);
  const rgb = new Uint8Array(w * h * 3);
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const s = ((h - 1 - y) * w + x) * 4, d = (y * w + x) * 3;
      rgb[d] = rgba[s]; rgb[d + 1] = rgba[s + 1]; rgb[d + 2] = rgba[s + 2];
    }
  }
  let text = '';
  for (let i = 0; i < rgb.length; i += 0x8000) text += String.fromCharCode(...rgb.subarray(i, i + 0x8000));
  return { width: w, height: h, rgb: btoa(text) };
}
