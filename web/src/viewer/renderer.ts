// The WebGL2 renderer of a baked asset: LOD meshes, the BTF maps as float textures decoded
// by shaders/btf.frag (seed 001 §3.4, Eq. 7), or the UsdPreviewSurface fallback (albedo +
// normal map) when the bake has no BTF; and the decode check (one fragment per atlas texel,
// raw f as floats) that tests compare with the CPU's `btf_lookup_texels`.
import type { Manifest } from "../api/viewer";
import { compile, floatArrayTexture, floatTexture, imageTexture, toLayers } from "./gl";
import { fromAngles, lookAt, multiply, perspective } from "./math";
import btfFrag from "./shaders/btf.frag?raw";
import meshVert from "./shaders/mesh.vert?raw";
import previewFrag from "./shaders/preview.frag?raw";
import quadVert from "./shaders/quad.vert?raw";

export const CORNER_FLOATS = 14; // services/viewer_data.py CORNER_FLOATS
const EIGEN_WIDTH = 1024;

export interface ViewState {
  azimuth: number;
  elevation: number;
  distance: number; // in bounding radii
  lightAzimuth: number;
  lightElevation: number;
  exposure: number;
  lambdaBias: number;
  mode: "btf" | "preview";
  /** -1: the LOD mesh by distance (`lodFor`); else the index of M_(i+1) */
  lod: number;
}

export interface Inputs {
  manifest: Manifest;
  lods: Float32Array[];
  frames: Float32Array;
  albedo: ImageBitmap;
  normal: ImageBitmap;
  btf: null | { weights: Float32Array; eigen: Float32Array; lut: Float32Array; pairIndex: Float32Array; meanTable: Float32Array };
}

interface Mesh {
  vao: WebGLVertexArrayObject;
  count: number;
}

export class BakeRenderer {
  readonly gl: WebGL2RenderingContext;
  readonly center: number[];
  readonly radius: number;
  private meshes: Mesh[] = [];
  private btfProg: WebGLProgram | null = null;
  private previewProg: WebGLProgram;
  private decodeProg: WebGLProgram | null = null;
  private tex: Record<string, WebGLTexture> = {};
  lastLod = 0;

  constructor(readonly canvas: HTMLCanvasElement, readonly inp: Inputs) {
    const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.gl = gl;
    const [lo, hi] = inp.manifest.lods[0].bounds;
    this.center = [0, 1, 2].map((i) => (lo[i] + hi[i]) / 2);
    this.radius = Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2 || 1;
    for (const data of inp.lods) this.meshes.push(this.upload(data));
    this.previewProg = compile(gl, meshVert, previewFrag);
    this.tex.albedo = imageTexture(gl, inp.albedo);
    this.tex.normal = imageTexture(gl, inp.normal);
    const n = inp.manifest.atlas;
    // frames: (N*N, 3, 3) -> 3 layers (t, b, n rows) of N x N RGB
    const fr = new Float32Array(3 * n * n * 3);
    for (let i = 0; i < n * n; i++) for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) fr[(r * n * n + i) * 3 + c] = inp.frames[i * 9 + r * 3 + c];
    this.tex.frames = floatArrayTexture(gl, n, n, 3, 3, fr);
    if (inp.btf && inp.manifest.btf) this.setupBtf();
  }

  get lodCount(): number {
    return this.meshes.length;
  }

  get hasBtf(): boolean {
    return this.btfProg !== null;
  }

  private upload(data: Float32Array): Mesh {
    const gl = this.gl;
    const vao = gl.createVertexArray()!;
    gl.bindVertexArray(vao);
    const buf = gl.createBuffer()!;
    gl.bindBuffer(gl.ARRAY_BUFFER, buf);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    const stride = CORNER_FLOATS * 4;
    const attrs: [number, number, number][] = [[0, 3, 0], [1, 2, 3], [2, 3, 5], [3, 3, 8], [4, 3, 11]];
    for (const [loc, size, off] of attrs) {
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, size, gl.FLOAT, false, stride, off * 4);
    }
    gl.bindVertexArray(null);
    return { vao, count: data.length / CORNER_FLOATS };
  }

  private setupBtf() {
    const gl = this.gl;
    const b = this.inp.manifest.btf!;
    const d = this.inp.btf!;
    this.btfProg = compile(gl, meshVert, btfFrag);
    this.decodeProg = compile(gl, quadVert, btfFrag);
    const [ch, cw, c] = b.weights.shape;
    const w = toLayers(d.weights, ch, cw, c);
    this.tex.weights = floatArrayTexture(gl, cw, ch, w.layers, 4, w.data);
    // eigen (L, d, C) -> rows of EIGEN_WIDTH pairs per level
    const [L, np] = b.eigen.shape;
    const width = Math.min(np, EIGEN_WIDTH);
    const rows = Math.ceil(np / width);
    const packed = new Float32Array(L * rows * width * c);
    for (let k = 0; k < L; k++)
      for (let p = 0; p < np; p++) {
        const dst = ((k * rows + Math.floor(p / width)) * width + (p % width)) * c;
        packed.set(d.eigen.subarray((k * np + p) * c, (k * np + p + 1) * c), dst);
      }
    const e = toLayers(packed, L * rows, width, c);
    this.tex.eigen = floatArrayTexture(gl, width, L * rows, e.layers, 4, e.data);
    const [R] = b.lut.shape;
    this.tex.lut = floatTexture(gl, R, R, 2, d.lut);
    const [nl, nv] = b.pair_index.shape;
    this.tex.pairIndex = floatTexture(gl, nv, nl, 1, d.pairIndex);
    const mt = new Float32Array(rows * width * 3);
    mt.set(d.meanTable);
    this.tex.meanTable = floatTexture(gl, width, rows, 3, mt);
    for (const prog of [this.btfProg, this.decodeProg]) {
      gl.useProgram(prog);
      const u = (name: string) => gl.getUniformLocation(prog, name);
      gl.uniform1i(u("uN"), this.inp.manifest.atlas);
      gl.uniform1i(u("uTopLevel"), b.top_level);
      b.weight_offsets.forEach(([y, x], k) => gl.uniform2i(u(`uLevelOffset[${k}]`), x, y));
      gl.uniform1i(u("uChannels"), b.channels);
      gl.uniform3i(u("uNComp"), ...b.n_components);
      gl.uniform1i(u("uEigenWidth"), width);
      gl.uniform1i(u("uEigenRows"), rows);
      gl.uniform1i(u("uLutRes"), R);
      const models: Record<string, number> = { phong: 0, constant: 1, table: 2 };
      b.mean_models.forEach((m, i) => {
        gl.uniform1i(u(`uMeanModel[${i}]`), models[m]);
        gl.uniform4fv(u(`uMeanParams[${i}]`), b.mean_params[i]);
      });
      const M = b.rgb_from_ycbcr;
      gl.uniformMatrix3fv(u("uRgbFromYcbcr"), false, [M[0][0], M[1][0], M[2][0], M[0][1], M[1][1], M[2][1], M[0][2], M[1][2], M[2][2]]);
      gl.uniform1f(u("uGrazingCos"), b.grazing_cos);
      this.bindBtfTextures(prog);
    }
  }

  private bindBtfTextures(prog: WebGLProgram) {
    const gl = this.gl;
    const units: [string, string, number][] = [
      ["uWeights", "weights", gl.TEXTURE_2D_ARRAY],
      ["uEigen", "eigen", gl.TEXTURE_2D_ARRAY],
      ["uLut", "lut", gl.TEXTURE_2D],
      ["uPairIndex", "pairIndex", gl.TEXTURE_2D],
      ["uMeanTable", "meanTable", gl.TEXTURE_2D],
      ["uFrames", "frames", gl.TEXTURE_2D_ARRAY],
    ];
    gl.useProgram(prog);
    units.forEach(([name, key, target], i) => {
      gl.activeTexture(gl.TEXTURE0 + i);
      gl.bindTexture(target, this.tex[key]);
      gl.uniform1i(gl.getUniformLocation(prog, name), i);
    });
  }

  /** Which LOD mesh a camera at `distance` bounding radii draws: M1 up close, one level
   * coarser per doubling of the distance beyond 4 radii. */
  lodFor(distance: number): number {
    return Math.max(0, Math.min(this.meshes.length - 1, Math.floor(Math.log2(Math.max(distance, 1e-6) / 4)) + 1));
  }

  draw(v: ViewState, pass = 0, size?: [number, number]): void {
    const gl = this.gl;
    const c = this.canvas;
    const [w, h] = size ?? [c.width, c.height];
    gl.viewport(0, 0, w, h);
    if (pass === 0) gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (pass === 0) {
      gl.clearColor(0.06, 0.07, 0.09, 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    }
    gl.enable(gl.DEPTH_TEST);
    const dir = fromAngles(v.azimuth, v.elevation);
    const dist = v.distance * this.radius;
    const eye = [0, 1, 2].map((i) => this.center[i] + dir[i] * dist);
    const proj = perspective((35 * Math.PI) / 180, w / h, dist / 100, dist + 4 * this.radius);
    const vp = multiply(proj, lookAt(eye, this.center, [0, 1, 0]));
    const btf = v.mode === "btf" && this.btfProg !== null;
    const prog = btf ? this.btfProg! : this.previewProg;
    if (btf) this.bindBtfTextures(prog);
    else {
      gl.useProgram(prog);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.tex.albedo);
      gl.uniform1i(gl.getUniformLocation(prog, "uAlbedo"), 0);
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, this.tex.normal);
      gl.uniform1i(gl.getUniformLocation(prog, "uNormalMap"), 1);
    }
    const u = (name: string) => gl.getUniformLocation(prog, name);
    gl.uniformMatrix4fv(u("uViewProj"), false, vp);
    gl.uniform3fv(u("uLightDir"), fromAngles(v.lightAzimuth, v.lightElevation));
    gl.uniform1f(u("uIrradiance"), 3.0);
    gl.uniform1f(u("uExposure"), v.exposure);
    if (btf) {
      gl.uniform3fv(u("uEye"), eye);
      gl.uniform1f(u("u_lambda_bias"), v.lambdaBias);
      gl.uniform1i(u("uDecode"), pass);
    }
    this.lastLod = v.lod >= 0 ? Math.min(v.lod, this.meshes.length - 1) : this.lodFor(v.distance);
    const mesh = this.meshes[this.lastLod];
    gl.bindVertexArray(mesh.vao);
    gl.drawArrays(gl.TRIANGLES, 0, mesh.count);
    gl.bindVertexArray(null);
  }

  /** The view check: the BTF view drawn at w x h into a float framebuffer three times: f
   * (linear RGB after max(., 0), before the light and exposure), (u, v, λ), and wo (world);
   * each (w*h*4) floats from the bottom row; the eye and the light direction used. */
  capture(v: ViewState, w: number, h: number): { f: Float32Array; uvl: Float32Array; wo: Float32Array; eye: number[]; light: number[] } {
    const gl = this.gl;
    if (!this.btfProg) throw new Error("this bake has no BTF maps");
    if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("EXT_color_buffer_float is not available");
    const target = gl.createTexture()!;
    gl.bindTexture(gl.TEXTURE_2D, target);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, w, h, 0, gl.RGBA, gl.FLOAT, null);
    const depth = gl.createRenderbuffer()!;
    gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
    const fbo = gl.createFramebuffer()!;
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, target, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    const out: Float32Array[] = [];
    for (const pass of [2, 3, 4]) {
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      this.draw({ ...v, mode: "btf" }, pass, [w, h]);
      const px = new Float32Array(w * h * 4);
      gl.readPixels(0, 0, w, h, gl.RGBA, gl.FLOAT, px);
      out.push(px);
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.deleteFramebuffer(fbo);
    gl.deleteRenderbuffer(depth);
    gl.deleteTexture(target);
    const dir = fromAngles(v.azimuth, v.elevation);
    const dist = v.distance * this.radius;
    const eye = [0, 1, 2].map((i) => this.center[i] + dir[i] * dist);
    return { f: out[0], uvl: out[1], wo: out[2], eye, light: fromAngles(v.lightAzimuth, v.lightElevation) };
  }

  /** The decode check: f (linear RGB, unclamped) of every finest texel at one pair of texel-
   * frame directions and one λ, as (N*N*4) floats, row-major from row 0 (v = 1). */
  decode(wi: number[], wo: number[], lambda: number): Float32Array {
    const gl = this.gl;
    if (!this.decodeProg) throw new Error("this bake has no BTF maps");
    if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("EXT_color_buffer_float is not available");
    const n = this.inp.manifest.atlas;
    const target = gl.createTexture()!;
    gl.bindTexture(gl.TEXTURE_2D, target);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, n, n, 0, gl.RGBA, gl.FLOAT, null);
    const fbo = gl.createFramebuffer()!;
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, target, 0);
    gl.viewport(0, 0, n, n);
    gl.disable(gl.DEPTH_TEST);
    const prog = this.decodeProg;
    this.bindBtfTextures(prog);
    gl.uniform1i(gl.getUniformLocation(prog, "uDecode"), 1);
    gl.uniform3fv(gl.getUniformLocation(prog, "uWiLocal"), wi);
    gl.uniform3fv(gl.getUniformLocation(prog, "uWoLocal"), wo);
    gl.uniform1f(gl.getUniformLocation(prog, "u_lambda"), lambda);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    const out = new Float32Array(n * n * 4);
    gl.readPixels(0, 0, n, n, gl.RGBA, gl.FLOAT, out);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.deleteFramebuffer(fbo);
    gl.deleteTexture(target);
    return out;
  }
}
