// An unmodified node-opcua client (npm) against geo-server's OPC UA server: connect
// without security, browse the machine's X axis, read TEMPC::coefficient with its
// EngineeringUnits and EURange, write it, read it back, write a value out of range.
// Prints one line "RESULT <JSON>" with what it saw (node-opcua logs to stdout too); tests/test_opcua_node.py checks it.
// Usage: node opcua_client_check.js <endpoint URL>
const {
  OPCUAClient,
  AttributeIds,
  DataType,
  MessageSecurityMode,
  SecurityPolicy,
} = require("node-opcua-client");

async function main() {
  const endpoint = process.argv[2];
  const client = OPCUAClient.create({
    endpointMustExist: false,
    securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    connectionStrategy: { maxRetry: 1, initialDelay: 100, maxDelay: 500 },
  });
  const out = {};
  await client.connect(endpoint);
  const session = await client.createSession();
  const nsArray = await session.readNamespaceArray();
  const ns = nsArray.indexOf("urn:geo-server:cnc");
  out.ns = ns;
  const axis = `ns=${ns};s=local/Axes/X/TEMPC`;
  const browsed = await session.browse(axis);
  out.browse = browsed.references.map((r) => r.browseName.name).sort();
  const coef = `ns=${ns};s=local/Axes/X/TEMPC/coefficient`;
  const props = await session.browse(coef);
  const byName = {};
  for (const r of props.references) byName[r.browseName.name] = r.nodeId.toString();
  const units = await session.read({ nodeId: byName.EngineeringUnits, attributeId: AttributeIds.Value });
  out.units = units.value.value.displayName.text;
  const range = await session.read({ nodeId: byName.EURange, attributeId: AttributeIds.Value });
  out.range = [range.value.value.low, range.value.value.high];
  out.before = (await session.read({ nodeId: coef, attributeId: AttributeIds.Value })).value.value;
  const value = Number(process.argv[3] || "12.5");
  const written = await session.write({
    nodeId: coef,
    attributeId: AttributeIds.Value,
    value: { value: { dataType: DataType.Double, value } },
  });
  out.write = written.name;
  const tooBig = await session.write({
    nodeId: coef,
    attributeId: AttributeIds.Value,
    value: { value: { dataType: DataType.Double, value: 1e9 } },
  });
  out.writeOutOfRange = tooBig.name;
  // the write is applied by the next GEO cycle: read until it shows (the server runs)
  for (let i = 0; i < 200; i++) {
    out.after = (await session.read({ nodeId: coef, attributeId: AttributeIds.Value })).value.value;
    if (out.after === value) break;
    await new Promise((r) => setTimeout(r, 10));
  }
  await session.close();
  await client.disconnect();
  console.log("RESULT " + JSON.stringify(out));
}

main().catch((err) => {
  console.error(err && err.stack ? err.stack : String(err));
  process.exit(1);
});
