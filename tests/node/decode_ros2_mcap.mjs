// Decode every message of an MCAP file of ROS 2 messages the way Foxglove does: @mcap/core reads the file
// (indexed reader, its CRCs checked), @foxglove/rosmsg parses each channel's ros2msg schema and
// @foxglove/rosmsg2-serialization decodes the CDR. Prints one JSON object: per topic the schema name, the
// message count and every message (typed arrays as plain arrays, NaN as null, bigint as string); exits 1 with
// a message on stderr on the first schema or message it cannot decode.
// Usage: node decode_ros2_mcap.mjs FILE.mcap
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";

const path = process.argv[2];
const handle = await open(path, "r");
const size = BigInt((await handle.stat()).size);
const readable = {
  size: async () => size,
  read: async (offset, length) => {
    const buffer = new Uint8Array(Number(length));
    await handle.read(buffer, 0, Number(length), Number(offset));
    return buffer;
  },
};
const reader = await McapIndexedReader.Initialize({ readable });
const readers = new Map();
const out = {};
for (const [id, channel] of reader.channelsById) {
  const schema = reader.schemasById.get(channel.schemaId);
  if (channel.messageEncoding !== "cdr" || schema.encoding !== "ros2msg") {
    console.error(`${channel.topic}: encoding ${channel.messageEncoding}/${schema.encoding}, not cdr/ros2msg`);
    process.exit(1);
  }
  const definition = new TextDecoder().decode(schema.data);
  readers.set(id, new MessageReader(parse(definition, { ros2: true })));
  out[channel.topic] = { schema: schema.name, count: 0, messages: [] };
}
const plain = (_key, value) => {
  if (typeof value === "bigint") return value.toString();
  if (ArrayBuffer.isView(value)) return Array.from(value, (v) => (typeof v === "bigint" ? v.toString() : v));
  return value;
};
for await (const message of reader.readMessages()) {
  const channel = reader.channelsById.get(message.channelId);
  let decoded;
  try {
    decoded = readers.get(message.channelId).readMessage(message.data);
  } catch (err) {
    console.error(`${channel.topic} at ${message.logTime}: ${err}`);
    process.exit(1);
  }
  const topic = out[channel.topic];
  topic.count += 1;
  topic.messages.push({ logTime: message.logTime.toString(), message: decoded });
}
process.stdout.write(JSON.stringify(out, plain));
