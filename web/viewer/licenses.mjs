// Writes the licences of everything bundled into viewer.js next to it (run by `npm run build`).
import { readFileSync, writeFileSync } from "node:fs";

const OUT = "../../service/web/static/viewer/THIRD_PARTY_LICENSES.txt";
const BUNDLED = ["three", "@sparkjsdev/spark", "fflate"];
const parts = BUNDLED.map((name) => {
  const pkg = JSON.parse(readFileSync(`node_modules/${name}/package.json`, "utf8"));
  const text = readFileSync(`node_modules/${name}/LICENSE`, "utf8").trim();
  return `${name} ${pkg.version} (${pkg.license})\n${"-".repeat(60)}\n${text}\n`;
});
writeFileSync(OUT, `viewer.js bundles these packages:\n\n${parts.join("\n")}`);
