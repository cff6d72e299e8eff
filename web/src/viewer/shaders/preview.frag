#version 300 es
// The UsdPreviewSurface fallback of a bake without BTF maps: the baked albedo and
// tangent-space normal maps on the LOD mesh (texelbake/baselines/normal_maps.py: n stored as
// (t . n_s, b . n_s, n . n_s) in [-1, 1], encoded to [0, 1]); diffuse, one distant light.
precision highp float;

in vec3 vPosition;
in vec2 vUv;
in vec3 vNormal;
in vec3 vTangent;
in vec3 vBitangent;
out vec4 fragColor;

uniform sampler2D uAlbedo;      // sRGB
uniform sampler2D uNormalMap;   // linear, (n + 1) / 2
uniform vec3 uLightDir;
uniform float uIrradiance;
uniform float uExposure;

const float PI = 3.14159265358979;

void main() {
  vec2 uv = vec2(vUv.x, 1.0 - vUv.y);   // row 0 of the maps at v = 1
  vec3 albedo = pow(texture(uAlbedo, uv).rgb, vec3(2.2));
  vec3 nt = texture(uNormalMap, uv).rgb * 2.0 - 1.0;
  vec3 n = normalize(nt.x * vTangent + nt.y * vBitangent + nt.z * vNormal);
  float cosi = max(dot(n, normalize(uLightDir)), 0.0);
  vec3 radiance = uIrradiance * albedo / PI * cosi * uExposure;
  fragColor = vec4(pow(clamp(radiance, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
