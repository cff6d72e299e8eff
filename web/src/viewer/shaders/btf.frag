#version 300 es
// The Laplacian BTF of seed 001 §3.4, decoded per fragment (texelbake/btf/render.py):
//   f(p, wi, wo) = sum_{k} w_k D_k(p)^T E_k(T_pc) + mu'(wi, wo),  w_k = clamp(1 - λ + k, 0, 1)  (Eq. 7)
// then YCbCr -> RGB. D_k: the level-k PCA weights of the texel holding p (finest texel (r, c)
// -> (r >> k, c >> k)); E_k(T_pc): the eigen Laplacian BRDFs at the pair found through the
// direction look-up tables (nearest, the seed's look-up); mu': the top-level mean (Phong,
// constant or tabulated per channel). wi, wo in the texel's frame (rows t, b, n).
precision highp float;
precision highp int;
precision highp sampler2D;
precision highp sampler2DArray;

in vec3 vPosition;
in vec2 vUv;
in vec3 vNormal;
in vec3 vTangent;
in vec3 vBitangent;
out vec4 fragColor;

uniform sampler2DArray uWeights;   // packed PCA weights of every level, 4 channels a layer
uniform sampler2DArray uEigen;     // eigen BRDFs: row k * uEigenRows + p / uEigenWidth
uniform sampler2D uLut;            // R x R: nearest light (r) and view (g) direction
uniform sampler2D uPairIndex;      // (n_l rows, n_v columns): column of the pair
uniform sampler2D uMeanTable;      // tabulated mean (rgb = Y, Cb, Cr) at pair p, wrapped
uniform sampler2DArray uFrames;    // N x N texel frames: layer 0 t, 1 b, 2 n (world -> texel)

uniform int uN;                    // finest atlas side
uniform int uTopLevel;             // λ_max
uniform ivec2 uLevelOffset[8];     // (x, y) of level k in uWeights
uniform int uChannels;
uniform ivec3 uNComp;              // components of Y, Cb, Cr
uniform int uEigenWidth;
uniform int uEigenRows;
uniform int uLutRes;
uniform int uMeanModel[3];         // 0 phong, 1 constant, 2 table
uniform vec4 uMeanParams[3];       // (ka, kd, ks, alpha) / (c, 0, 0, 0)
uniform mat3 uRgbFromYcbcr;
uniform float uGrazingCos;

uniform vec3 uEye;
uniform vec3 uLightDir;            // world, towards the light
uniform float uIrradiance;
uniform float uExposure;
uniform float u_lambda_bias;       // λ bias, added to the footprint's λ
uniform int uDecode;               // 1: the decode check (one fragment per texel, raw f);
                                   // 2, 3, 4: the view check: f, (u, v, λ), wo (world)
uniform vec3 uWiLocal;             // decode check: directions in the texel frame
uniform vec3 uWoLocal;
uniform float u_lambda;            // decode check: λ

ivec2 lutCell(vec3 w) {
  // equal-area (Lambert azimuthal) disk of the hemisphere (texelbake/btf/lut.py to_disk)
  vec2 xy = w.xy / sqrt(1.0 + clamp(w.z, 0.0, 1.0));
  ivec2 ij = ivec2(floor((xy + 1.0) * 0.5 * float(uLutRes)));
  return clamp(ij, ivec2(0), ivec2(uLutRes - 1));   // (x = column, y = row)
}

int pairOf(vec3 wi, vec3 wo) {
  int light = int(texelFetch(uLut, lutCell(wi), 0).r + 0.5);
  int view = int(texelFetch(uLut, lutCell(wo), 0).g + 0.5);
  return int(floor(texelFetch(uPairIndex, ivec2(view, light), 0).r + 0.5));
}

float meanChannel(int c, vec3 wi, vec3 wo, int pair) {
  int model = uMeanModel[c];
  vec4 q = uMeanParams[c];
  if (model == 1) return q.x;
  if (model == 2) {
    ivec2 at = ivec2(pair % uEigenWidth, pair / uEigenWidth);
    return texelFetch(uMeanTable, at, 0)[c];
  }
  vec3 h = wi + wo;
  float hn = length(h);
  float ndh = hn > 0.0 ? clamp(h.z / hn, 0.0, 1.0) : 0.0;
  return q.x + q.y * clamp(wi.z, 0.0, 1.0) + q.z * pow(ndh, q.w);   // Eq. 5
}

// f in YCbCr at finest texel (row, col), directions in the texel frame, λ
vec3 btfYcc(int row, int col, vec3 wi, vec3 wo, float lambda) {
  if (wi.z <= uGrazingCos || wo.z <= uGrazingCos) return vec3(0.0);
  int pair = pairOf(wi, wo);
  if (pair < 0) return vec3(0.0);
  float lam = clamp(lambda, 0.0, float(uTopLevel));
  vec3 ycc = vec3(0.0);
  int layers = (uChannels + 3) / 4;
  for (int k = 0; k <= uTopLevel; k++) {
    float w_k = clamp(1.0 - lam + float(k), 0.0, 1.0);   // Eq. 7
    if (w_k <= 0.0) continue;
    ivec2 dt = uLevelOffset[k] + ivec2(col >> k, row >> k);
    ivec2 et = ivec2(pair % uEigenWidth, k * uEigenRows + pair / uEigenWidth);
    vec3 level = vec3(0.0);
    for (int g = 0; g < layers; g++) {
      vec4 d = texelFetch(uWeights, ivec3(dt, g), 0);
      vec4 e = texelFetch(uEigen, ivec3(et, g), 0);
      vec4 de = d * e;
      for (int j = 0; j < 4; j++) {
        int c = 4 * g + j;
        if (c >= uChannels) break;
        if (c < uNComp.x) level.x += de[j];
        else if (c < uNComp.x + uNComp.y) level.y += de[j];
        else level.z += de[j];
      }
    }
    ycc += w_k * level;
  }
  return ycc + vec3(meanChannel(0, wi, wo, pair), meanChannel(1, wi, wo, pair),
                    meanChannel(2, wi, wo, pair));
}

void main() {
  if (uDecode == 1) {
    int col = int(gl_FragCoord.x);
    int row = int(gl_FragCoord.y);
    fragColor = vec4(uRgbFromYcbcr * btfYcc(row, col, uWiLocal, uWoLocal, u_lambda), 1.0);
    return;
  }
  int n = uN;
  int row = clamp(int(floor((1.0 - vUv.y) * float(n))), 0, n - 1);   // row 0 at v = 1
  int col = clamp(int(floor(vUv.x * float(n))), 0, n - 1);
  vec3 t = texelFetch(uFrames, ivec3(col, row, 0), 0).xyz;
  vec3 b = texelFetch(uFrames, ivec3(col, row, 1), 0).xyz;
  vec3 nn = texelFetch(uFrames, ivec3(col, row, 2), 0).xyz;
  vec3 wo = normalize(uEye - vPosition);
  vec3 wi = normalize(uLightDir);
  vec3 wiL = vec3(dot(t, wi), dot(b, wi), dot(nn, wi));
  vec3 woL = vec3(dot(t, wo), dot(b, wo), dot(nn, wo));
  // continuous LOD: λ = log2 of the pixel's footprint in finest texels
  vec2 st = vUv * float(n);
  float footprint = max(length(dFdx(st)), length(dFdy(st)));
  float lambda = log2(max(footprint, 1e-6)) + u_lambda_bias;
  vec3 f = max(uRgbFromYcbcr * btfYcc(row, col, wiL, woL, lambda), 0.0);  // f carries cos_i cos_o
  if (uDecode == 2) { fragColor = vec4(f, 1.0); return; }
  if (uDecode == 3) { fragColor = vec4(vUv, lambda, 1.0); return; }
  if (uDecode == 4) { fragColor = vec4(wo, 1.0); return; }
  vec3 radiance = uIrradiance * f * uExposure;
  fragColor = vec4(pow(clamp(radiance, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
