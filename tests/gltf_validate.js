// Validate glTF files with the Khronos glTF validator (installed by `make bootstrap` into .tools/).
// Prints one JSON line per file: {"file", "errors", "warnings", "messages": [first errors and warnings]}.
const path = require('path');
const fs = require('fs');
const validator = require(path.join(__dirname, '..', '.tools', 'node_modules', 'gltf-validator'));

(async () => {
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {maxIssues: 100});
    const messages = report.issues.messages.filter((m) => m.severity <= 1).slice(0, 20)
      .map((m) => `${m.code} ${m.pointer || ''}: ${m.message}`);
    console.log(JSON.stringify({file, errors: report.issues.numErrors, warnings: report.issues.numWarnings,
      messages}));
  }
})().catch((e) => { console.error(e); process.exit(1); });
