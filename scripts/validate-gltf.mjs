// Runs the Khronos glTF validator (npm package `gltf-validator`) on each file named on the
// command line: prints one summary line per file (errors, warnings, infos, hints) and
// every issue, and exits with status 1 when a file has an error, 2 on a usage or
// installation problem. Called by scripts/validate-gltf.sh, which installs the validator.
import { createRequire } from 'node:module';
import { readFile } from 'node:fs/promises';
import path from 'node:path';

const dir = process.env.GLTF_VALIDATOR_DIR;
if (!dir) {
  console.error('validate-gltf: set GLTF_VALIDATOR_DIR to the folder holding node_modules/gltf-validator');
  process.exit(2);
}
const require = createRequire(path.join(path.resolve(dir), 'package.json'));
const validator = require('gltf-validator');
const files = process.argv.slice(2);
if (files.length === 0) {
  console.error('usage: validate-gltf.mjs FILE.glb...');
  process.exit(2);
}
let failed = false;
for (const file of files) {
  const bytes = new Uint8Array(await readFile(file));
  const report = await validator.validateBytes(bytes, { maxIssues: 100 });
  const i = report.issues;
  console.log(
    `${file}: ${i.numErrors} errors, ${i.numWarnings} warnings, ${i.numInfos} infos, ` +
      `${i.numHints} hints (gltf-validator ${report.validatorVersion}; ` +
      `${report.info.drawCallCount} draw calls, ${report.info.totalVertexCount} vertices, ` +
      `${report.info.totalTriangleCount} triangles)`
  );
  const severity = ['error', 'warning', 'info', 'hint'];
  for (const m of i.messages) {
    console.log(`  ${severity[m.severity]} ${m.code} at ${m.pointer ?? m.offset ?? ''}: ${m.message}`);
  }
  if (i.numErrors > 0) failed = true;
}
process.exit(failed ? 1 : 0);
