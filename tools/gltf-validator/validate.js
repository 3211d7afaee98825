#!/usr/bin/env node
// Validate one .glb/.gltf file with the Khronos glTF validator (npm gltf-validator, pinned in
// package-lock.json) and print its report as JSON on stdout. Exit status: 0 when the file was
// validated (whatever it contains; read report.issues.numErrors), 2 when it could not be read
// or the validator could not run. Used by recon.export.validate_gltf.
//   node tools/gltf-validator/validate.js path/to/asset.glb [maxIssues]
'use strict';
const fs = require('fs');
const path = require('path');
const validator = require('gltf-validator');

const file = process.argv[2];
const maxIssues = parseInt(process.argv[3] || '100', 10);
if (!file) {
  console.error('usage: validate.js FILE.glb|FILE.gltf [maxIssues]');
  process.exit(2);
}
let bytes;
try {
  bytes = new Uint8Array(fs.readFileSync(file));
} catch (err) {
  console.error(`${file}: cannot read (${err.message})`);
  process.exit(2);
}
validator.validateBytes(bytes, {
  uri: path.basename(file),
  maxIssues: maxIssues,
  // Resources referenced by a .gltf (buffers, images) are read relative to the file.
  externalResourceFunction: (uri) => new Promise((resolve, reject) => {
    const full = path.resolve(path.dirname(file), decodeURIComponent(uri));
    fs.readFile(full, (err, data) => (err ? reject(err.toString()) : resolve(new Uint8Array(data))));
  }),
}).then((report) => {
  process.stdout.write(JSON.stringify(report));
  process.stdout.write('\n');
}, (err) => {
  console.error(`${file}: the validator could not run (${err})`);
  process.exit(2);
});
