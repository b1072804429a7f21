// Load a .glb with three.js's GLTFLoader, play its first animation to a time and print the point
// positions of the first object with a position attribute there (morph targets applied), as JSON.
import { readFileSync } from "node:fs";
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";

const [path, timeArg] = process.argv.slice(2);
const data = readFileSync(path);
const buffer = data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength);
new GLTFLoader().parse(buffer, "", (gltf) => {
  let points = null;
  gltf.scene.traverse((o) => { if (!points && o.geometry) points = o; });
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const clip = gltf.animations[0];
  if (clip) { mixer.clipAction(clip).play(); mixer.setTime(Number(timeArg ?? 0)); }
  const base = points.geometry.attributes.position;
  const morphs = points.geometry.morphAttributes.position ?? [];
  const w = points.morphTargetInfluences ?? [];
  const out = [];
  for (let i = 0; i < base.count; i++) {
    const p = [base.getX(i), base.getY(i), base.getZ(i)];
    morphs.forEach((m, k) => { p[0] += w[k] * m.getX(i); p[1] += w[k] * m.getY(i); p[2] += w[k] * m.getZ(i); });
    out.push(p);
  }
  console.log(JSON.stringify({ type: points.type, count: base.count, morphs: morphs.length,
    duration: clip ? clip.duration : 0, positions: out }));
}, (err) => { console.error(String(err)); process.exit(1); });
