// A dtx bag read with the official MCAP TypeScript reader, knowing only docs/bag-format.md:
//   node read_bag.mjs BAG      prints {stream: {...}, indexed: {...} | null} as one JSON line
// The stream reader reads any bag, also one cut short by a crash; the indexed reader needs the
// summary a finished recording ends with (null when the bag has none).
import { readFileSync } from "node:fs";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { loadDecompressHandlers } from "@mcap/support";
import { decode } from "@msgpack/msgpack";

const LENGTH_BYTES = 8;

/** A dtx record's frames: repeat { uint64 LE length, bytes }. */
function frames(data) {
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const out = [];
  for (let offset = 0; offset < data.byteLength;) {
    const length = Number(view.getBigUint64(offset, true));
    out.push(data.subarray(offset + LENGTH_BYTES, offset + LENGTH_BYTES + length));
    offset += LENGTH_BYTES + length;
  }
  return out;
}

/** Decode one dtx message from the record and its schema alone; count and check it. */
function tally(summary, schema, channel, message) {
  const topic = (summary.topics[channel.topic] ??= { count: 0, schema: schema.name, encoding: schema.encoding });
  topic.count++;
  if (channel.messageEncoding !== "dtx/msgpack+buffers") return;
  const description = JSON.parse(new TextDecoder().decode(schema.data));
  const [headerFrame, ...buffers] = frames(message.data);
  const header = decode(headerFrame, { useBigInt64: true });
  if (header.s !== description.title) throw new Error(`${channel.topic}: header says ${header.s}`);
  for (const [name, field] of Object.entries(description.properties)) {
    if (!(name in header.d)) throw new Error(`${channel.topic}: field ${name} missing`);
    if (field["x-dtx-array"]) {
      const index = header.d[name].__array__;
      const [dtype, shape] = header.a[index];
      const itemsize = Number(dtype.slice(2));
      if (buffers[index].byteLength !== itemsize * shape.reduce((a, b) => a * b, 1)) {
        throw new Error(`${channel.topic}.${name}: buffer size does not match ${dtype} ${shape}`);
      }
    }
  }
  summary.decoded++;
}

const data = new Uint8Array(readFileSync(process.argv[2]));
// lz4 and zstd chunks, as Foxglove Studio decompresses them.
const decompressHandlers = await loadDecompressHandlers();

const stream = { topics: {}, decoded: 0, done: false };
const reader = new McapStreamReader({ validateCrcs: true, decompressHandlers });
reader.append(data);
const schemas = new Map();
const channels = new Map();
for (let record; (record = reader.nextRecord());) {
  if (record.type === "Schema") schemas.set(record.id, record);
  else if (record.type === "Channel") channels.set(record.id, record);
  else if (record.type === "Message") {
    const channel = channels.get(record.channelId);
    tally(stream, schemas.get(channel.schemaId), channel, record);
  }
}
stream.done = reader.done();

let indexed = null;
try {
  const readable = {
    size: async () => BigInt(data.byteLength),
    read: async (offset, size) => data.subarray(Number(offset), Number(offset + size)),
  };
  const bag = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  indexed = { topics: {}, decoded: 0 };
  for await (const message of bag.readMessages()) {
    const channel = bag.channelsById.get(message.channelId);
    tally(indexed, bag.schemasById.get(channel.schemaId), channel, message);
  }
} catch (error) {
  if (stream.done) throw error; // a finished bag must read indexed too
}
process.stdout.write(JSON.stringify({ stream, indexed }) + "\n");
