// Validates glTF files with the Khronos glTF validator and prints one JSON line per file:
// {file, errors, warnings, messages}. Usage: node validate_gltf.js FILE...
const fs = require("fs");
const validator = require("gltf-validator");

(async () => {
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)));
    const issues = report.issues;
    console.log(
      JSON.stringify({
        file,
        errors: issues.numErrors,
        warnings: issues.numWarnings,
        messages: issues.messages,
        animations: report.info ? report.info.animationCount : null,
      })
    );
  }
})().catch((e) => {
  console.error(e);
  process.exit(1);
});
