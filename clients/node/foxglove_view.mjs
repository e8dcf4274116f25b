// A Foxglove viewer made of the official @foxglove/ws-protocol client, as Foxglove Studio 1.x
// and Lichtblick connect: it subscribes to every channel as soon as it is advertised, decodes
// each protobuf message with the schema its channel advertised (protobufjs, as the app reads a
// FileDescriptorSet), and reports what arrived, per channel and per frame.
//   node foxglove_view.mjs URL SUBPROTOCOL SECONDS   prints one JSON line
// It reports after SECONDS, or as soon as the server closes a connection that was open. Until
// the first connection opens it tries again every 100 ms, so it can be started before the server.
import wsProtocol from "@foxglove/ws-protocol";
import protobuf from "protobufjs";
import descriptor from "protobufjs/ext/descriptor/index.js";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, subprotocol, seconds] = process.argv.slice(2);
// frames: channel topic -> frame key -> messages. A frame key is the message's frame_id, or
// "parent->child" for a FrameTransform (a transform names two frames). longest_gap_s: channel
// topic -> frame key -> the longest wait between two of its messages, in seconds.
const result = {
  subprotocol,
  opened: false,
  advertised: [],
  messages: {},
  frames: {},
  longest_gap_s: {},
  errors: [],
  statuses: [],
};
const lastArrival = new Map(); // "topic frame key" -> performance.now() of its last message

function report() {
  process.stdout.write(JSON.stringify(result) + "\n");
  process.exit(0);
}

// Fields keep their schema names (snake_case): protobufjs reads them from the descriptor.
function frameKey(message) {
  if ("child_frame_id" in message) {
    return `${message.parent_frame_id}->${message.child_frame_id}`;
  }
  return message.frame_id ?? "";
}

function schemaType(channel) {
  if (channel.encoding !== "protobuf") {
    return undefined;
  }
  const bytes = Buffer.from(channel.schema, "base64");
  const root = protobuf.Root.fromDescriptor(descriptor.FileDescriptorSet.decode(bytes));
  return root.lookupType(channel.schemaName);
}

function connect() {
  const client = new FoxgloveClient({ ws: new WebSocket(url, [subprotocol]) });
  const channelOf = new Map(); // subscription id -> { topic, type }
  client.on("open", () => {
    result.opened = true;
  });
  client.on("error", (error) => {
    if (result.opened) {
      result.errors.push(String(error?.message ?? error));
    }
  });
  client.on("close", () => (result.opened ? report() : setTimeout(connect, 100)));
  client.on("status", (status) => result.statuses.push(status.message));
  client.on("advertise", (channels) => {
    for (const channel of channels) {
      result.advertised.push(channel.topic);
      const id = client.subscribe(channel.id);
      channelOf.set(id, { topic: channel.topic, type: schemaType(channel) });
    }
  });
  client.on("message", ({ subscriptionId, data }) => {
    const { topic, type } = channelOf.get(subscriptionId);
    result.messages[topic] = (result.messages[topic] ?? 0) + 1;
    if (type !== undefined) {
      const key = frameKey(type.decode(new Uint8Array(data.buffer, data.byteOffset, data.byteLength)));
      const frames = (result.frames[topic] ??= {});
      frames[key] = (frames[key] ?? 0) + 1;
      const now = performance.now();
      const last = lastArrival.get(`${topic} ${key}`);
      if (last !== undefined) {
        const gaps = (result.longest_gap_s[topic] ??= {});
        gaps[key] = Math.max(gaps[key] ?? 0, (now - last) / 1000);
      }
      lastArrival.set(`${topic} ${key}`, now);
    }
  });
}

connect();
setTimeout(report, Number(seconds) * 1000);
