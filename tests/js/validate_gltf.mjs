// Validate a glTF/GLB with the Khronos validator; print its report summary as JSON (exit 1 on errors).
import { readFileSync } from "node:fs";
import validator from "gltf-validator";

const path = process.argv[2];
const report = await validator.validateBytes(new Uint8Array(readFileSync(path)), { maxIssues: 50 });
const issues = report.issues;
console.log(JSON.stringify({ errors: issues.numErrors, warnings: issues.numWarnings, infos: issues.numInfos,
  messages: issues.messages.map((m) => `${m.code} ${m.pointer ?? ""} ${m.message}`) }));
process.exit(issues.numErrors > 0 ? 1 : 0);
