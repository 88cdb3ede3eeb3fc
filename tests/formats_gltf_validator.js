// Runs Khronos's glTF-Validator (the npm package `gltf-validator`) on GLB files and prints
// one JSON report line per file; exits 1 when any file has an error or a warning.
// Usage: MESHSTREAM_GLTF_VALIDATOR=/path/to/node_modules/gltf-validator node this.js a.glb ...
'use strict';
const fs = require('fs');
const validator = require(process.env.MESHSTREAM_GLTF_VALIDATOR);

(async () => {
  let failed = false;
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)));
    const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
    console.log(JSON.stringify({ file, numErrors, numWarnings, numInfos, numHints, messages }));
    failed = failed || numErrors > 0 || numWarnings > 0;
  }
  process.exit(failed ? 1 : 0);
})().catch((e) => {
  console.error(e);
  process.exit(2);
});
