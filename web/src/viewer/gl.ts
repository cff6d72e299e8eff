// Small WebGL2 helpers: programs, float textures (sampled with texelFetch only).

export function compile(gl: WebGL2RenderingContext, vs: string, fs: string): WebGLProgram {
  const make = (type: number, src: string) => {
    const s = gl.createShader(type)!;
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`shader: ${gl.getShaderInfoLog(s)}`);
    return s;
  };
  const p = gl.createProgram()!;
  gl.attachShader(p, make(gl.VERTEX_SHADER, vs));
  gl.attachShader(p, make(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`program: ${gl.getProgramInfoLog(p)}`);
  return p;
}

function nearest(gl: WebGL2RenderingContext, target: number) {
  gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.texParameteri(target, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(target, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
}

const FORMATS: Record<number, [number, number]> = {
  1: [WebGL2RenderingContext.R32F, WebGL2RenderingContext.RED],
  2: [WebGL2RenderingContext.RG32F, WebGL2RenderingContext.RG],
  3: [WebGL2RenderingContext.RGB32F, WebGL2RenderingContext.RGB],
  4: [WebGL2RenderingContext.RGBA32F, WebGL2RenderingContext.RGBA],
};

/** A float 2-D texture of `channels` (1-4) per texel, row-major from row 0. */
export function floatTexture(gl: WebGL2RenderingContext, w: number, h: number, channels: number, data: Float32Array): WebGLTexture {
  const t = gl.createTexture()!;
  gl.bindTexture(gl.TEXTURE_2D, t);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  const [internal, format] = FORMATS[channels];
  gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, gl.FLOAT, data);
  nearest(gl, gl.TEXTURE_2D);
  return t;
}

/** A float 2-D array texture: `layers` of w x h RGBA (or RGB) texels. */
export function floatArrayTexture(gl: WebGL2RenderingContext, w: number, h: number, layers: number, channels: 3 | 4, data: Float32Array): WebGLTexture {
  const t = gl.createTexture()!;
  gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  const [internal, format] = FORMATS[channels];
  gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, internal, w, h, layers, 0, format, gl.FLOAT, data);
  nearest(gl, gl.TEXTURE_2D_ARRAY);
  return t;
}

/** (rows, cols, C) channel-last floats -> ceil(C/4) layers of (rows, cols, 4). */
export function toLayers(src: Float32Array, rows: number, cols: number, c: number): { data: Float32Array; layers: number } {
  const layers = Math.ceil(c / 4);
  const out = new Float32Array(layers * rows * cols * 4);
  for (let i = 0; i < rows * cols; i++)
    for (let ch = 0; ch < c; ch++) out[((ch >> 2) * rows * cols + i) * 4 + (ch & 3)] = src[i * c + ch];
  return { data: out, layers };
}

export function imageTexture(gl: WebGL2RenderingContext, img: ImageBitmap): WebGLTexture {
  const t = gl.createTexture()!;
  gl.bindTexture(gl.TEXTURE_2D, t);
  gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, img);
  nearest(gl, gl.TEXTURE_2D);
  return t;
}
