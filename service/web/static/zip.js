// A minimal zip writer (stored entries, no compression: photos are compressed already) so that picked files or
// a picked folder upload as one archive, which is what POST /v1/jobs takes. Each file is read once for its
// CRC-32; the Blob then refers to the File objects themselves, so the browser need not hold them all in memory.
// Without Zip64 an archive is limited to 65535 entries and 4 GiB, far above the service's own caps.

const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[n] = c >>> 0;
  }
  return t;
})();

export function crc32(bytes, crc = 0) {
  let c = ~crc >>> 0;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
  return ~c >>> 0;
}

const LIMIT = 0xffffffff;

function header(size) {
  const buf = new ArrayBuffer(size);
  return [new DataView(buf), new Uint8Array(buf)];
}

// files: [{name, file}] (name: the path inside the archive, '/'-separated). Returns a Blob (application/zip).
export async function storeZip(files, onFile = () => {}) {
  if (files.length > 0xffff) throw new Error("too many files for one archive (65535 at most)");
  const enc = new TextEncoder();
  const parts = [];
  const central = [];
  let offset = 0;
  for (const [i, { name, file }] of files.entries()) {
    const data = new Uint8Array(await file.arrayBuffer());
    const crc = crc32(data);
    const fname = enc.encode(name);
    if (offset + 30 + fname.length + data.length > LIMIT) throw new Error("the files exceed 4 GiB: upload an archive");
    const [lv, lb] = header(30 + fname.length);
    lv.setUint32(0, 0x04034b50, true);
    lv.setUint16(4, 20, true);        // version needed
    lv.setUint16(6, 0x0800, true);    // flags: UTF-8 names
    lv.setUint16(8, 0, true);         // stored
    lv.setUint32(14, crc, true);
    lv.setUint32(18, data.length, true);
    lv.setUint32(22, data.length, true);
    lv.setUint16(26, fname.length, true);
    lb.set(fname, 30);
    parts.push(lb, file);
    const [cv, cb] = header(46 + fname.length);
    cv.setUint32(0, 0x02014b50, true);
    cv.setUint16(4, 20, true);
    cv.setUint16(6, 20, true);
    cv.setUint16(8, 0x0800, true);
    cv.setUint32(16, crc, true);
    cv.setUint32(20, data.length, true);
    cv.setUint32(24, data.length, true);
    cv.setUint16(28, fname.length, true);
    cv.setUint32(42, offset, true);
    cb.set(fname, 46);
    central.push(cb);
    offset += lb.length + data.length;
    onFile(i + 1, files.length);
  }
  const size = central.reduce((s, c) => s + c.length, 0);
  const [ev, eb] = header(22);
  ev.setUint32(0, 0x06054b50, true);
  ev.setUint16(8, files.length, true);
  ev.setUint16(10, files.length, true);
  ev.setUint32(12, size, true);
  ev.setUint32(16, offset, true);
  return new Blob([...parts, ...central, eb], { type: "application/zip" });
}
