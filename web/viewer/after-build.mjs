// Run by `npm run build` after esbuild: writes next to viewer.js
// - THIRD_PARTY_LICENSES.txt, the licences of everything bundled;
// - BUILD.json, the SHA-256 of the sources the bundle was built from (tests/service/test_viewer.py recomputes it,
//   so a change to src/ or the lock file without a rebuild fails CI, which never runs npm).
import { createHash } from "node:crypto";
import { readdirSync, readFileSync, writeFileSync } from "node:fs";

const OUT = "../../service/web/static/viewer";
const BUNDLED = ["three", "@sparkjsdev/spark", "fflate"];

const parts = BUNDLED.map((name) => {
  const pkg = JSON.parse(readFileSync(`node_modules/${name}/package.json`, "utf8"));
  const text = readFileSync(`node_modules/${name}/LICENSE`, "utf8").trim();
  return `${name} ${pkg.version} (${pkg.license})\n${"-".repeat(60)}\n${text}\n`;
});
writeFileSync(`${OUT}/THIRD_PARTY_LICENSES.txt`, `viewer.js bundles these packages:\n\n${parts.join("\n")}`);

// the same digest as tests/service/test_viewer.py::_source_digest: "path\0bytes\0" for each file, sorted by path
const files = ["package.json", "package-lock.json", ...readdirSync("src").sort().map((f) => `src/${f}`)].sort();
const hash = createHash("sha256");
for (const f of files) {
  hash.update(`${f}\0`);
  hash.update(readFileSync(f));
  hash.update("\0");
}
const versions = Object.fromEntries(BUNDLED.map((n) => [n, JSON.parse(readFileSync(`node_modules/${n}/package.json`, "utf8")).version]));
writeFileSync(`${OUT}/BUILD.json`, JSON.stringify({ sources_sha256: hash.digest("hex"), files, versions }, null, 1) + "\n");
