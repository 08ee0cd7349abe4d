// Runs the Khronos glTF validator on a .glb and prints its report as JSON. The validator
// (2.0.0-dev.3.10) does not know KHR_gaussian_splatting yet and calls each of its
// `KHR_gaussian_splatting:*` attribute names invalid (glTF-Validator issue #252): those
// errors are listed apart; the exit status is 1 when any other error remains.
import { validateBytes } from "gltf-validator";
import { readFileSync } from "fs";

const bytes = new Uint8Array(readFileSync(process.argv[2]));
const report = await validateBytes(bytes, { maxIssues: 0, writeTimestamp: false });
const messages = report.issues.messages;
const splatAttribute = (m) => m.code === "MESH_PRIMITIVE_INVALID_ATTRIBUTE" &&
  /\/attributes\/KHR_gaussian_splatting:/.test(m.pointer ?? "");
const errors = messages.filter((m) => m.severity === 0 && !splatAttribute(m));
console.log(JSON.stringify({
  errors: errors.map((m) => `${m.code} ${m.pointer ?? ""}: ${m.message}`),
  splatAttributeErrors: messages.filter(splatAttribute).length,
  warnings: messages.filter((m) => m.severity === 1).map((m) => `${m.code} ${m.pointer ?? ""}`),
  unsupportedExtensions: messages.filter((m) => m.code === "UNSUPPORTED_EXTENSION").length,
}, null, 1));
process.exit(errors.length === 0 ? 0 : 1);
