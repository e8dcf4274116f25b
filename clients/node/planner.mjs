// A grasp planner in Node that calls /inference/estimate, written from docs/wire-protocol.md
// alone: it is the test that the page is enough for a client in another language.
//
//   node planner.mjs images MAPS.f32 N OUT.u8 [SIGMA_MM [UNCERTAINTY.f32]]
//                                                depth-maps (N x 100 x 100 <f4) -> images (|u1), their
//                                                geometry known to SIGMA_MM (§3; default -1: the checkpoint's);
//                                                the uncertainty (<f4, §3) -> UNCERTAINTY.f32 when it is
//                                                not absent; prints the regions ranked (§3 Uncertainty)
//   node planner.mjs malformed                   28 broken requests; prints how many got an error reply,
//                                                and the answer to dropout_samples 2 (refused since v4)
//   node planner.mjs steady COUNT                COUNT requests one after another, retrying by §4;
//                                                prints one line per answer, then a JSON summary
//   node planner.mjs cloud POINTS.f32 P POSES.f64 N COUNT OUT.u8
//                                                COUNT requests about one cloud (P x 3 <f4) at N gel
//                                                poses (<f8), by the cloud handle rule of §3; the
//                                                last reply's images -> OUT.u8
//
// The bus directory comes from DTX_BUS_DIR (or the default of §1). Output: one JSON line on stdout.
import { readFileSync, readdirSync, writeFileSync } from "node:fs";
import { hostname, tmpdir, userInfo } from "node:os";
import { join } from "node:path";
import { decode, encode } from "@msgpack/msgpack";

// §2: t is an int64 of nanoseconds, beyond a double's exact integers, so it travels as a BigInt.
const pack = (value) => Buffer.from(encode(value, { useBigInt64: true }));
const unpack = (bytes) => decode(bytes, { useBigInt64: true });
import { Dealer } from "zeromq";

const SERVICE = "/inference/estimate";
const REQUEST = "dtx.inference.TactileEstimateRequest";
const CHECK_MS = 250;

function busDir() {
  return process.env.DTX_BUS_DIR || join(tmpdir(), `dtx-${userInfo().uid}`, process.env.DTX_DOMAIN || "default");
}

function alive(pid) {
  try {
    process.kill(pid, 0);
    return true;
  } catch (error) {
    return error.code === "EPERM";
  }
}

/** Live server entries of the service (§1: skip entries whose pid is not running). */
function servers() {
  const folder = join(busDir(), "service", encodeURIComponent(SERVICE));
  let names = [];
  try {
    names = readdirSync(folder).filter((n) => n.endsWith(".json") && !n.startsWith("."));
  } catch {
    return [];
  }
  const found = [];
  for (const name of names.sort()) {
    try {
      const entry = JSON.parse(readFileSync(join(folder, name), "utf8"));
      if (alive(entry.pid)) found.push(entry);
    } catch {
      // being replaced or removed right now
    }
  }
  return found;
}

/** One DEALER per server entry, a receive loop each, replies matched by q. */
class Planner {
  constructor() {
    this.id = `node-planner-${hostname()}-${process.pid}-${Math.random().toString(36).slice(2)}`;
    this.q = 0;
    this.next = 0;
    this.connections = new Map(); // address -> {dealer, entry}
    this.waiting = new Map(); // q -> resolve
    this.computedTwiceRisk = 0;
  }

  connection(entry) {
    let conn = this.connections.get(entry.address);
    if (!conn) {
      const dealer = new Dealer({ linger: 0, immediate: true, sendTimeout: 1000 });
      dealer.connect(entry.address);
      conn = { dealer, entry };
      this.connections.set(entry.address, conn);
      this.receiveLoop(conn);
    }
    return conn;
  }

  async receiveLoop(conn) {
    try {
      for await (const frames of conn.dealer) {
        const header = unpack(frames[1]);
        const resolve = this.waiting.get(header.q) ?? (header.q === 0 ? this.waiting.get(conn.inFlight) : undefined);
        if (resolve) resolve({ header, buffers: frames.slice(2) });
      }
    } catch {
      // socket closed
    }
  }

  drop(address) {
    const conn = this.connections.get(address);
    if (conn) {
      this.connections.delete(address);
      conn.dealer.close();
    }
  }

  /** Send frames built by build(q, p, entry) for q = this.q, following §4's retry rule;
   * resolves with the reply and the server entry that answered. */
  async call(build, deadlineMs = 60000) {
    const q = ++this.q;
    const start = Date.now();
    const reply = new Promise((resolve) => this.waiting.set(q, resolve));
    let attempts = 0;
    try {
      while (Date.now() - start < deadlineMs) {
        const live = servers();
        if (live.length === 0) {
          await sleep(CHECK_MS);
          continue;
        }
        for (const address of this.connections.keys()) {
          if (!live.some((e) => e.address === address)) this.drop(address);
        }
        const entry = live[this.next++ % live.length];
        const conn = this.connection(entry);
        conn.inFlight = q;
        try {
          await conn.dealer.send(build(q, this.id, entry));
        } catch {
          await sleep(CHECK_MS);
          continue; // not connected (yet): look again
        }
        if (++attempts > 1) this.computedTwiceRisk++;
        // Wait while this worker lives; when its entry is gone, resend elsewhere at once.
        while (Date.now() - start < deadlineMs) {
          const answer = await Promise.race([reply, sleep(CHECK_MS)]);
          if (answer) return { ...answer, entry };
          const current = servers().find((e) => e.address === entry.address && e.pid === entry.pid);
          if (!current) break;
        }
      }
      return null;
    } finally {
      this.waiting.delete(q);
    }
  }

  close() {
    for (const address of [...this.connections.keys()]) this.drop(address);
  }
}

function sleep(ms) {
  return new Promise((resolve) => setTimeout(() => resolve(null), ms));
}

function header(q, p, fields, arrays) {
  return { s: REQUEST, v: 4, t: BigInt(Date.now()) * 1000000n, q, f: "", p, d: fields, a: arrays };
}

/** A well-formed request for depth-maps: the frames of §2 and §3. sigmaMm: §3's pose uncertainty.
 * dropout_samples is always 1 (§3: any other value is refused; the uncertainty comes anyway). */
function depthRequest(maps, n, sigmaMm = -1) {
  return (q, p) => [
    Buffer.from(SERVICE),
    pack(header(q, p, {
      depth_maps: { __array__: 0 }, points: { __array__: 1 }, cloud_id: "", gel_poses: { __array__: 2 },
      dropout_samples: 1, pose_sigma_mm: sigmaMm,
    }, [["<f4", [n, 100, 100]], ["<f4", [0, 3]], ["<f8", [0, 4, 4]]])),
    Buffer.from(maps.buffer, maps.byteOffset, maps.byteLength),
    Buffer.alloc(0),
    Buffer.alloc(0),
  ];
}

/** A request about a cloud: its points (P x 3 <f4) when withPoints, else only its id (§3). */
function cloudRequest(points, p3, poses, n, cloudId, withPoints) {
  return (q, p) => [
    Buffer.from(SERVICE),
    pack(header(q, p, {
      depth_maps: { __array__: 0 }, points: { __array__: 1 }, cloud_id: cloudId, gel_poses: { __array__: 2 },
      dropout_samples: 1, pose_sigma_mm: -1,
    }, [["<f4", [0, 100, 100]], ["<f4", [withPoints ? p3 : 0, 3]], ["<f8", [n, 4, 4]]])),
    Buffer.alloc(0),
    withPoints ? Buffer.from(points.buffer, points.byteOffset, points.byteLength) : Buffer.alloc(0),
    Buffer.from(poses.buffer, poses.byteOffset, poses.byteLength),
  ];
}

function replyArray(reply, field) {
  const index = reply.header.d[field].__array__;
  return reply.buffers[index];
}

function replyShape(reply, field) {
  return reply.header.a[reply.header.d[field].__array__];
}

/** How far each region's image departs from the gel at rest, in image levels: the mean absolute
 * difference of its pixels from their own per-channel median (a contact covers a minority of
 * the gel). images: N x 100 x 100 x 3 |u1, C order. */
function contactSignal(images, n) {
  const pixels = 100 * 100;
  const signal = [];
  for (let r = 0; r < n; r++) {
    let total = 0;
    for (let c = 0; c < 3; c++) {
      const values = new Float64Array(pixels);
      for (let k = 0; k < pixels; k++) values[k] = images[(r * pixels + k) * 3 + c];
      const sorted = Float64Array.from(values).sort();
      const median = (sorted[pixels / 2 - 1] + sorted[pixels / 2]) / 2;
      for (let k = 0; k < pixels; k++) total += Math.abs(values[k] - median);
    }
    signal.push(total / (3 * pixels));
  }
  return signal;
}

/** The candidate regions, best first (§3 Uncertainty): each reachable region scored by its
 * image's contact signal less its region_uncertainty (both image levels: the signal it surely
 * shows), the out-of-reach ones last. With uncertainty_status "absent" the server has no
 * uncertainty: the regions are scored by the signal alone and the ranking says so; a region is
 * never taken as certain. */
function rankRegions(d, signal) {
  if (d.uncertainty_status !== "ok" && d.uncertainty_status !== "absent") {
    throw new Error(`unknown uncertainty_status ${JSON.stringify(d.uncertainty_status)}`);
  }
  const ok = d.uncertainty_status === "ok";
  const score = signal.map((s, i) => (ok ? s - d.region_uncertainty[i] : s));
  const order = score.map((_, i) => i);
  const reachable = (i) => (d.region_status[i] === "ok" ? 0 : 1);
  order.sort((a, b) => reachable(a) - reachable(b) || score[b] - score[a] || a - b);
  return { order, score, by: ok ? "contact signal - region_uncertainty" : "contact signal (uncertainty absent)" };
}

async function images(mapsPath, n, outPath, sigmaMm, uncertaintyPath) {
  const planner = new Planner();
  const raw = readFileSync(mapsPath);
  const maps = new Float32Array(raw.buffer, raw.byteOffset, raw.byteLength / 4);
  const reply = await planner.call(depthRequest(maps, n, sigmaMm));
  planner.close();
  if (!reply) throw new Error("no reply");
  if (reply.header.s !== "dtx.inference.TactileEstimateReply") throw new Error(JSON.stringify(reply.header.d));
  const d = reply.header.d;
  const pixels = replyArray(reply, "images");
  writeFileSync(outPath, pixels);
  // §3: "ok" carries u for every region; "absent" an empty array and no region means.
  const [dtype, shape] = replyShape(reply, "uncertainty");
  const expected = d.uncertainty_status === "ok" ? [n, 100, 100] : [0, 100, 100];
  const regions = d.uncertainty_status === "ok" ? n : 0;
  if (dtype !== "<f4" || JSON.stringify(shape) !== JSON.stringify(expected) || d.region_uncertainty.length !== regions) {
    throw new Error(`uncertainty ${dtype} ${JSON.stringify(shape)} does not fit its status ${d.uncertainty_status}`);
  }
  if (uncertaintyPath && d.uncertainty_status === "ok") writeFileSync(uncertaintyPath, replyArray(reply, "uncertainty"));
  return { schema: reply.header.s, a: reply.header.a, region_status: d.region_status,
           pose_sigma_mm: d.pose_sigma_mm, serves: d.serves, uncertainty_status: d.uncertainty_status,
           region_uncertainty: d.region_uncertainty, region_points: d.region_points,
           region_surface_bins: d.region_surface_bins, ranking: rankRegions(d, contactSignal(pixels, n)) };
}

/** 28 requests, each broken one way (§2, §3); every one must get an error reply. */
function malformedVariants() {
  const maps = new Float32Array(100 * 100).fill(0.001);
  const good = depthRequest(maps, 1);
  const edit = (change) => (q, p) => {
    const frames = good(q, p);
    const h = unpack(frames[1]);
    const result = change(h, frames) ?? frames;
    if (result === frames) frames[1] = pack(h);
    return result;
  };
  const big = Buffer.from(maps.buffer.slice(0));
  for (let i = 0; i < big.length; i += 4) big.writeFloatBE(0.001, i);
  return {
    "header not msgpack": (q, p) => [Buffer.from(SERVICE), Buffer.from([0xc1, 0x00, 0xff])],
    "header not a map": (q, p) => [Buffer.from(SERVICE), pack([q, p])],
    "s missing": edit((h) => { delete h.s; }),
    "unknown schema": edit((h) => { h.s = "dtx.nothing.Here"; }),
    "v 99": edit((h) => { h.v = 99; }),
    "v a string": edit((h) => { h.v = "1"; }),
    "t a float": edit((h) => { h.t = 1.5; }),
    "t negative": edit((h) => { h.t = -1; }),
    "f an int": edit((h) => { h.f = 3; }),
    "p an int": edit((h) => { h.p = 7; }),
    "d missing": edit((h) => { delete h.d; }),
    "d field missing": edit((h) => { delete h.d.dropout_samples; }),
    "d field extra": edit((h) => { h.d.colour = "red"; }),
    "d field of another type": edit((h) => { h.d.dropout_samples = "1"; }),
    "a missing": edit((h) => { delete h.a; }),
    "big-endian array": edit((h, frames) => { h.a[0][0] = ">f4"; frames[1] = pack(h); frames[2] = big; return frames; }),
    "dtype not allowed": edit((h) => { h.a[0][0] = "<c8"; }),
    "shape and byte count differ": edit((h) => { h.a[0][1] = [2, 100, 100]; }),
    "buffers missing": edit((h, frames) => { frames[1] = pack(h); return frames.slice(0, 3); }),
    "buffer extra": edit((h, frames) => { frames[1] = pack(h); return [...frames, Buffer.alloc(0)]; }),
    "array reference out of range": edit((h) => { h.d.depth_maps = { __array__: 7 }; }),
    "array referenced twice": edit((h) => { h.d.points = { __array__: 0 }; }),
    "negative dimension": edit((h) => { h.a[1][1] = [-1, 3]; }),
    "depth-maps of the wrong size": (q, p) => depthRequest(new Float32Array(50 * 50), 1)(q, p).map((f, i) =>
      i === 1 ? pack({ ...unpack(f), a: [["<f4", [1, 50, 50]], ["<f4", [0, 3]], ["<f8", [0, 4, 4]]] }) : f),
    "depth-maps not finite": depthRequest(new Float32Array(100 * 100).fill(NaN), 1),
    "pose_sigma_mm above 5 mm": depthRequest(maps, 1, 5.5),
    "pose_sigma_mm not finite": depthRequest(maps, 1, NaN),
    "pose_sigma_mm a string": edit((h) => { h.d.pose_sigma_mm = "0"; }),
  };
}

async function malformed() {
  const planner = new Planner();
  const results = {};
  for (const [name, build] of Object.entries(malformedVariants())) {
    const reply = await planner.call(build, 20000);
    results[name] = reply ? { q: reply.header.q, schema: reply.header.s, code: reply.header.d?.code, text: reply.header.d?.text } : null;
  }
  // The server serves on: a good request after all of them.
  const after = await planner.call(depthRequest(new Float32Array(100 * 100).fill(0.001), 1));
  // §3: a well-formed v4 request still asking for dropout samples is refused, saying why.
  const good = depthRequest(new Float32Array(100 * 100).fill(0.001), 1);
  const dropout = await planner.call((q, p) => {
    const frames = good(q, p);
    const h = unpack(frames[1]);
    h.d.dropout_samples = 2;
    frames[1] = pack(h);
    return frames;
  }, 20000);
  planner.close();
  const variants = Object.keys(results).length;
  const answered = Object.values(results).filter((r) => r && r.schema === "dtx.system.ServiceError" && r.code === "bad_request").length;
  return { variants, answered, served_after: after?.header.s === "dtx.inference.TactileEstimateReply", results,
           dropout_samples_2: dropout ? { schema: dropout.header.s, code: dropout.header.d?.code, text: dropout.header.d?.text } : null };
}

async function steady(count) {
  const planner = new Planner();
  // Sixteen regions: long enough that a kill can land mid-request.
  const maps = new Float32Array(16 * 100 * 100).fill(0.001);
  let lost = 0;
  const servedBy = {};
  for (let i = 0; i < count; i++) {
    const reply = await planner.call(depthRequest(maps, 16), 60000);
    if (!reply || reply.header.s !== "dtx.inference.TactileEstimateReply") {
      lost++;
    } else {
      const worker = reply.header.d.worker;
      servedBy[worker] = (servedBy[worker] ?? 0) + 1;
    }
    process.stderr.write(`answered ${i + 1}\n`);
  }
  planner.close();
  return { count, lost, served_by: servedBy, resent_after_a_worker_died: planner.computedTwiceRisk };
}

/** §3's cloud handle rule: a connection that has not answered about the cloud gets its points
 * (and its id once known); one that has, the id alone; unknown_cloud: that one no longer holds
 * it, so its next request carries the points again. */
async function cloud(pointsPath, p3, posesPath, n, count, outPath) {
  const planner = new Planner();
  const raw = readFileSync(pointsPath);
  const points = new Float32Array(raw.buffer, raw.byteOffset, raw.byteLength / 4);
  const rawPoses = readFileSync(posesPath);
  const poses = new Float64Array(rawPoses.buffer, rawPoses.byteOffset, rawPoses.byteLength / 8);
  let cloudId = "";
  const holding = new Set(); // addresses whose worker answered with cloudId
  let withPoints = 0;
  let idOnly = 0;
  let refused = 0;
  let last = null;
  const send = (entry, forcePoints) => {
    const points_ = forcePoints || !cloudId || !holding.has(entry.address);
    if (points_) withPoints++;
    else idOnly++;
    return cloudRequest(points, p3, poses, n, cloudId, points_);
  };
  for (let i = 0; i < count; i++) {
    let reply = await planner.call((q, p, entry) => send(entry, false)(q, p));
    if (reply?.header.d?.code === "unknown_cloud") {
      refused++;
      holding.delete(reply.entry.address);
      reply = await planner.call((q, p, entry) => send(entry, true)(q, p));
    }
    if (!reply || reply.header.s !== "dtx.inference.TactileEstimateReply") throw new Error(JSON.stringify(reply?.header.d));
    if (reply.header.d.cloud_id !== cloudId) holding.clear();
    cloudId = reply.header.d.cloud_id;
    holding.add(reply.entry.address);
    last = reply;
  }
  // A cloud no worker holds: refused with unknown_cloud, for the client to send the points.
  const unknown = await planner.call(cloudRequest(points, p3, poses, n, "0".repeat(64), false));
  planner.close();
  writeFileSync(outPath, replyArray(last, "images"));
  // §3's geometry counts: how many points and surface bins each estimate rests on.
  const { region_points: regionPoints, region_surface_bins: surfaceBins } = last.header.d;
  return { cloud_id: cloudId, with_points: withPoints, id_only: idOnly, refused, worker: last.header.d.worker,
           unknown_id: unknown?.header.d?.code, region_points: regionPoints, region_surface_bins: surfaceBins };
}

const [mode, ...args] = process.argv.slice(2);
let result;
if (mode === "images") result = await images(args[0], Number(args[1]), args[2], Number(args[3] ?? -1), args[4]);
else if (mode === "malformed") result = await malformed();
else if (mode === "steady") result = await steady(Number(args[0]));
else if (mode === "cloud") result = await cloud(args[0], Number(args[1]), args[2], Number(args[3]), Number(args[4]), args[5]);
else throw new Error(`unknown mode ${mode}`);
process.stdout.write(JSON.stringify(result) + "\n");
process.exit(0);
