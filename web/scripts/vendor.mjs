// Copies the pinned three.js files the page imports from node_modules/three into web/vendor/three,
// where mrptv embeds them (the server needs no npm and no internet at run time).
//   node scripts/vendor.mjs           copy (after changing the pinned version in package.json)
//   node scripts/vendor.mjs --check   fail if the vendored copy differs from node_modules
import { readFileSync, writeFileSync, mkdirSync } from 'node:fs';
import { dirname, join } from 'node:path';
import { fileURLToPath } from 'node:url';

const web = join(dirname(fileURLToPath(import.meta.url)), '..');
const from = join(web, 'node_modules', 'three');
const to = join(web, 'vendor', 'three');
const FILES = [
  ['build/three.module.js', 'three.module.js'],
  ['build/three.core.js', 'three.core.js'],
  ['examples/jsm/controls/OrbitControls.js', 'OrbitControls.js'],
  ['LICENSE', 'LICENSE'],
  ['package.json', 'package.json'],
];

const check = process.argv.includes('--check');
let stale = 0;
for (const [src, dst] of FILES) {
  let bytes;
  try {
    bytes = readFileSync(join(from, src));
  } catch (e) {
    console.error(`cannot read ${join(from, src)}: ${e.message} (run: npm ci --prefix web)`);
    process.exit(2);
  }
  const target = join(to, dst);
  if (check) {
    let have = null;
    try { have = readFileSync(target); } catch { /* missing counts as stale */ }
    if (!have || !have.equals(bytes)) {
      console.error(`web/vendor/three/${dst} differs from node_modules/three/${src}`);
      stale++;
    }
  } else {
    mkdirSync(dirname(target), { recursive: true });
    writeFileSync(target, bytes);
  }
}
if (check && stale) {
  console.error('run: npm --prefix web run vendor');
  process.exit(1);
}
const version = JSON.parse(readFileSync(join(from, 'package.json'), 'utf8')).version;
console.log(`${check ? 'vendored three.js matches' : 'vendored'} three ${version}`);
