// A Foxglove viewer made of the official @foxglove/ws-protocol client, as Foxglove Studio 1.x
// and Lichtblick connect: it subscribes to every channel as soon as it is advertised and
// reports what arrived.
//   node foxglove_view.mjs URL SUBPROTOCOL SECONDS   prints one JSON line
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol;

const [url, subprotocol, seconds] = process.argv.slice(2);
const client = new FoxgloveClient({ ws: new WebSocket(url, [subprotocol]) });
const result = { subprotocol, opened: false, advertised: [], messages: {}, errors: [], statuses: [] };
const topicOf = new Map();
client.on("open", () => { result.opened = true; });
client.on("error", (error) => result.errors.push(String(error?.message ?? error)));
client.on("status", (status) => result.statuses.push(status.message));
client.on("advertise", (channels) => {
  for (const channel of channels) {
    result.advertised.push(channel.topic);
    const id = client.subscribe(channel.id);
    topicOf.set(id, channel.topic);
  }
});
client.on("message", ({ subscriptionId }) => {
  const topic = topicOf.get(subscriptionId);
  result.messages[topic] = (result.messages[topic] ?? 0) + 1;
});
setTimeout(() => {
  process.stdout.write(JSON.stringify(result) + "\n");
  process.exit(0);
}, Number(seconds) * 1000);
