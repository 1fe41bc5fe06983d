// Validate a glTF/GLB file with the Khronos glTF validator and print its report.
//
//   node tests/gltf_validate.mjs FILE.glb
//
// Prints the validator's report as JSON on stdout (exit 0 whatever the issues;
// the caller reads report.issues.numErrors / numWarnings / numInfos / numHints).
// Exit 2: bad usage or the `gltf-validator` npm package is missing (run
// `npm install` at the repository root); exit 3: the validator refused the
// input (not glTF at all).
//
// The package is resolved from the repository's node_modules (the folder
// above tests/), whatever the current directory is.

import { readFile } from "node:fs/promises";
import { createRequire } from "node:module";
import { basename } from "node:path";

const file = process.argv[2];
if (!file || process.argv.length > 3) {
  console.error("usage: node tests/gltf_validate.mjs FILE.glb");
  process.exit(2);
}

let validator;
try {
  // createRequire anchors resolution at this script, so Node walks up from
  // tests/ to the repository's node_modules.
  validator = createRequire(import.meta.url)("gltf-validator");
} catch (err) {
  console.error(`gltf-validator not found (run 'npm install' in the repository root): ${err.message}`);
  process.exit(2);
}

const bytes = new Uint8Array(await readFile(file));
try {
  const report = await validator.validateBytes(bytes, {
    uri: basename(file),
    maxIssues: 0, // report every issue, not the first 100
    writeTimestamp: false, // reproducible output
  });
  process.stdout.write(JSON.stringify(report, null, 2) + "\n");
} catch (err) {
  console.error(`validator rejected ${file}: ${err}`);
  process.exit(3);
}
