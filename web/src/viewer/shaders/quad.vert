#version 300 es
// A full-screen triangle (the BTF decode check draws one fragment per atlas texel); the mesh
// varyings are declared so the program links with btf.frag, which ignores them there.
const vec2 P[3] = vec2[3](vec2(-1.0, -1.0), vec2(3.0, -1.0), vec2(-1.0, 3.0));
out vec3 vPosition;
out vec2 vUv;
out vec3 vNormal;
out vec3 vTangent;
out vec3 vBitangent;
void main() {
  vPosition = vec3(0.0);
  vUv = vec2(0.0);
  vNormal = vec3(0.0, 0.0, 1.0);
  vTangent = vec3(1.0, 0.0, 0.0);
  vBitangent = vec3(0.0, 1.0, 0.0);
  gl_Position = vec4(P[gl_VertexID], 0.0, 1.0);
}
