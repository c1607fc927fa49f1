// Independent reader check: decode every message of a mocaprig recording with @mcap/core
// (TypeScript, from foxglove/mcap) and protobufjs, using only the schemas stored in the file.
// Usage: node check.mjs indexed|stream FILE.mcap  -> one JSON object on stdout:
//   {channels: {topic: {schema, count, first: <decoded, bytes as {bytes: n}>, bytes: total}},
//    metadata: [names], attachments: [names], done: bool}
import { open, readFile } from "node:fs/promises";
import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { FileHandleReadable } from "@mcap/nodejs";
import { loadDecompressHandlers, protobufFromBinaryDescriptor } from "@mcap/support";

const [, , mode, path] = process.argv;
const decompressHandlers = await loadDecompressHandlers();
const out = { channels: {}, metadata: [], attachments: [], done: true };
const types = new Map(); // schema id -> protobufjs Type

function plain(value) {
  if (value instanceof Uint8Array) return { bytes: value.length };
  if (Array.isArray(value)) return value.map(plain);
  if (value && typeof value === "object") {
    return Object.fromEntries(Object.entries(value).map(([k, v]) => [k, plain(v)]));
  }
  return value;
}

function typeFor(schema) {
  if (!types.has(schema.id)) {
    if (schema.encoding !== "protobuf") throw new Error(`schema ${schema.name}: ${schema.encoding}`);
    const root = protobufFromBinaryDescriptor(schema.data);
    types.set(schema.id, root.lookupType(schema.name));
  }
  return types.get(schema.id);
}

function take(channel, schema, message) {
  const type = typeFor(schema);
  const decoded = type.toObject(type.decode(message.data), { longs: String, defaults: true });
  const bytesTotal = Object.values(decoded)
    .filter((v) => v instanceof Uint8Array)
    .reduce((a, v) => a + v.length, 0);
  const entry = (out.channels[channel.topic] ??= { schema: schema.name, count: 0, bytes: 0 });
  if (entry.count === 0) entry.first = plain(decoded);
  entry.count += 1;
  entry.bytes += bytesTotal;
}

if (mode === "indexed") {
  const handle = await open(path, "r");
  const reader = await McapIndexedReader.Initialize({
    readable: new FileHandleReadable(handle),
    decompressHandlers,
  });
  for await (const message of reader.readMessages()) {
    const channel = reader.channelsById.get(message.channelId);
    take(channel, reader.schemasById.get(channel.schemaId), message);
  }
  for await (const m of reader.readMetadata()) out.metadata.push(m.name);
  for await (const a of reader.readAttachments()) out.attachments.push(a.name);
  await handle.close();
} else {
  const reader = new McapStreamReader({ decompressHandlers });
  reader.append(new Uint8Array(await readFile(path)));
  const schemas = new Map();
  const channels = new Map();
  for (let rec; (rec = reader.nextRecord()) !== undefined; ) {
    if (rec.type === "Schema") schemas.set(rec.id, rec);
    else if (rec.type === "Channel") channels.set(rec.id, rec);
    else if (rec.type === "Message") {
      const channel = channels.get(rec.channelId);
      take(channel, schemas.get(channel.schemaId), rec);
    } else if (rec.type === "Metadata") out.metadata.push(rec.name);
    else if (rec.type === "Attachment") out.attachments.push(rec.name);
  }
  out.done = reader.done();
}
process.stdout.write(JSON.stringify(out) + "\n");
