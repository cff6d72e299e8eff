#version 300 es
// The LOD mesh: position, atlas uv, and the face's tangent space (normal, tangent, bitangent).
layout(location = 0) in vec3 aPosition;
layout(location = 1) in vec2 aUv;
layout(location = 2) in vec3 aNormal;
layout(location = 3) in vec3 aTangent;
layout(location = 4) in vec3 aBitangent;

uniform mat4 uViewProj;

out vec3 vPosition;
out vec2 vUv;
out vec3 vNormal;
out vec3 vTangent;
out vec3 vBitangent;

void main() {
  vPosition = aPosition;
  vUv = aUv;
  vNormal = aNormal;
  vTangent = aTangent;
  vBitangent = aBitangent;
  gl_Position = uViewProj * vec4(aPosition, 1.0);
}
