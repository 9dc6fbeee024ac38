// Decode raw CDR samples (as a live ROS 2 publisher puts them on Zenoh) the way Foxglove does: @foxglove/rosmsg
// parses each type's ros2msg definition and @foxglove/rosmsg2-serialization decodes the bytes.
// Reads one JSON array on stdin, [{"definition": ".msg text with its dependencies", "data": "base64"}, ...];
// prints the decoded messages as one JSON array (typed arrays as plain arrays, NaN as null, bigint as string);
// exits 1 with a message on stderr on the first definition or sample it cannot decode.
// Usage: node decode_ros2_cdr.mjs < samples.json
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";

let input = "";
for await (const chunk of process.stdin) input += chunk;
const plain = (_key, value) => {
  if (typeof value === "bigint") return value.toString();
  if (ArrayBuffer.isView(value)) return Array.from(value, (v) => (typeof v === "bigint" ? v.toString() : v));
  return value;
};
const readers = new Map();
const out = [];
for (const [i, sample] of JSON.parse(input).entries()) {
  try {
    if (!readers.has(sample.definition)) {
      readers.set(sample.definition, new MessageReader(parse(sample.definition, { ros2: true })));
    }
    out.push(readers.get(sample.definition).readMessage(Buffer.from(sample.data, "base64")));
  } catch (err) {
    console.error(`sample ${i}: ${err}`);
    process.exit(1);
  }
}
process.stdout.write(JSON.stringify(out, plain));
