// Validate glTF 2.0 files with the Khronos glTF-Validator (npm gltf-validator): prints one JSON
// report per file (its issue counts and messages) and exits 1 when any file has errors.
// Usage: node web/validate.mjs FILE.glb [FILE.glb ...]
import { readFile } from 'node:fs/promises';
import path from 'node:path';
import validator from 'gltf-validator';

let errors = 0;
for (const file of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(await readFile(file)), {
    uri: path.basename(file),
    externalResourceFunction: (uri) => readFile(path.resolve(path.dirname(file), decodeURIComponent(uri))),
  });
  errors += report.issues.numErrors;
  console.log(JSON.stringify({ file, numErrors: report.issues.numErrors,
    numWarnings: report.issues.numWarnings, numInfos: report.issues.numInfos,
    messages: report.issues.messages.slice(0, 20) }));
}
process.exit(errors ? 1 : 0);
