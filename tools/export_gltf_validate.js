#!/usr/bin/env node
// Runs the Khronos glTF-Validator (npm `gltf-validator`) on each file given and prints one JSON
// line per file: {file, errors, warnings, infos, hints, messages}. Exit status 0 when every file
// has 0 errors and 0 warnings, 1 otherwise, 2 on a usage or read error.
'use strict';
const fs = require('fs');
const path = require('path');
const validator = require('gltf-validator');

async function validate(file) {
  const data = new Uint8Array(fs.readFileSync(file));
  const report = await validator.validateBytes(data, {
    uri: path.basename(file),
    // Every buffer we write is embedded (data: URI or GLB chunk); refuse anything external.
    externalResourceFunction: (uri) => Promise.reject(new Error(`unexpected external resource ${uri}`)),
  });
  const issues = report.issues;
  return {
    file,
    errors: issues.numErrors,
    warnings: issues.numWarnings,
    infos: issues.numInfos,
    hints: issues.numHints,
    messages: issues.messages.map((m) => `${m.severity} ${m.code} ${m.pointer || ''}: ${m.message}`),
  };
}

async function main() {
  const files = process.argv.slice(2);
  if (files.length === 0) {
    console.error('usage: node tools/export_gltf_validate.js FILE.gltf|FILE.glb ...');
    process.exit(2);
  }
  let ok = true;
  for (const file of files) {
    const r = await validate(file);
    console.log(JSON.stringify(r));
    if (r.errors > 0 || r.warnings > 0) ok = false;
  }
  process.exit(ok ? 0 : 1);
}

main().catch((e) => {
  console.error(String(e));
  process.exit(2);
});
