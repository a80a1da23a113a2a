// Validates glTF files with the Khronos glTF Validator (npm's gltf-validator, its node API `validateBytes`):
// prints a line of JSON for each file (its counts of errors, warnings, infos and hints, its issues, and what
// the validator read: vertices, triangles, images, extensions), and exits with 1 if a file has an error.
//
//   node tests/readers/validate_gltf.mjs FILE.glb...
import { readFile } from "node:fs/promises";
import { basename } from "node:path";
import validator from "gltf-validator";

let failed = false;
for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(await readFile(file)), {
        uri: basename(file),
        maxIssues: 0,
        writeTimestamp: false,
    });
    const { numErrors, numWarnings, numInfos, numHints, messages } = report.issues;
    const info = report.info ?? {};
    console.log(JSON.stringify({
        file,
        validator: report.validatorVersion,
        errors: numErrors,
        warnings: numWarnings,
        infos: numInfos,
        hints: numHints,
        issues: messages.map((m) => `${m.code} (${["error", "warning", "info", "hint"][m.severity]}) ${m.pointer ?? ""}: ${m.message}`),
        vertices: info.totalVertexCount,
        triangles: info.totalTriangleCount,
        images: (info.resources ?? []).filter((r) => r.image).map((r) => r.image),
        extensions: info.extensionsUsed ?? [],
    }));
    failed ||= numErrors > 0;
}
process.exit(failed ? 1 : 0);
