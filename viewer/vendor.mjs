// Copies the three.js files the viewer loads from node_modules (pinned by package-lock.json) into the
// package's static folder, with three.js's licence. Run after `npm ci`: `npm run vendor`.
import { copyFileSync, mkdirSync, readFileSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const three = join(here, "node_modules", "three");
const out = join(here, "..", "bodyfit", "api", "rest", "viewer", "vendor");
const files = {
  "build/three.module.min.js": "three.module.min.js",
  "build/three.core.min.js": "three.core.min.js",
  "examples/jsm/controls/OrbitControls.js": "OrbitControls.js",
  "examples/jsm/loaders/PLYLoader.js": "PLYLoader.js",
  "examples/jsm/loaders/OBJLoader.js": "OBJLoader.js",
  "examples/jsm/loaders/STLLoader.js": "STLLoader.js",
  "examples/jsm/loaders/PCDLoader.js": "PCDLoader.js",
  "LICENSE": "three.LICENSE.txt",
};
mkdirSync(out, { recursive: true });
for (const [from, to] of Object.entries(files)) copyFileSync(join(three, from), join(out, to));
const version = JSON.parse(readFileSync(join(three, "package.json"), "utf8")).version;
writeFileSync(join(out, "VERSION"), `three ${version}\n`);
console.log(`three ${version}: ${Object.keys(files).length} files -> ${out}`);
