// An unmodified node-opcua client (npm) walks browse paths that the test took from the
// OPC Foundation's NodeSet XML (tests/test_opcua_companion.py): for each path, given as
// [namespace URI, browse name] steps from the Objects folder, it translates the path on
// geo-server's server and reads the target's NodeClass, its TypeDefinition (as
// "<namespace URI>|<numeric id>") and, for a variable, the status of its value and
// whether the value is there.
// Prints one line "RESULT <JSON>": a list of {path, found, nodeClass, type, status, hasValue,
// variantType, isArray, dataType}.
// Usage: node opcua_companion_check.js <endpoint URL> <file with the JSON list of paths>
const fs = require("fs");
const {
  OPCUAClient,
  AttributeIds,
  BrowseDirection,
  MessageSecurityMode,
  SecurityPolicy,
} = require("node-opcua-client");

async function main() {
  const endpoint = process.argv[2];
  const paths = JSON.parse(fs.readFileSync(process.argv[3], "utf-8"));
  const client = OPCUAClient.create({
    endpointMustExist: false,
    securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None,
    connectionStrategy: { maxRetry: 1, initialDelay: 100, maxDelay: 500 },
  });
  await client.connect(endpoint);
  const session = await client.createSession();
  const nsArray = await session.readNamespaceArray();
  const out = [];
  for (const path of paths) {
    const elements = path.map(([uri, name]) => ({
      referenceTypeId: "i=33", // HierarchicalReferences
      isInverse: false,
      includeSubtypes: true,
      targetName: { namespaceIndex: nsArray.indexOf(uri), name },
    }));
    const found = await session.translateBrowsePath({
      startingNode: "i=85", // Objects
      relativePath: { elements },
    });
    const entry = { path, found: found.statusCode.name === "Good" && found.targets.length === 1 };
    if (entry.found) {
      const nodeId = found.targets[0].targetId.toString();
      const cls = await session.read({ nodeId, attributeId: AttributeIds.NodeClass });
      entry.nodeClass = cls.value.value;
      const typed = await session.browse({
        nodeId,
        browseDirection: BrowseDirection.Forward,
        referenceTypeId: "i=40", // HasTypeDefinition
        includeSubtypes: false,
        resultMask: 0x3f,
      });
      const t = typed.references.length ? typed.references[0].nodeId : null;
      entry.type = t ? `${nsArray[t.namespace]}|${t.value}` : null;
      if (entry.nodeClass === 2) {
        // a Variable: its value, and the value's type and shape beside the declared ones
        const dv = await session.read({ nodeId, attributeId: AttributeIds.Value });
        entry.status = dv.statusCode.name;
        entry.hasValue = dv.value.value !== null && dv.value.value !== undefined;
        entry.variantType = dv.value.dataType;
        entry.isArray = dv.value.arrayType !== 0; // (VariantArrayType.Scalar)
        const dt = (await session.read({ nodeId, attributeId: AttributeIds.DataType })).value.value;
        entry.dataType = `${nsArray[dt.namespace]}|${dt.value}`;
      }
    }
    out.push(entry);
  }
  await session.close();
  await client.disconnect();
  console.log("RESULT " + JSON.stringify(out));
}

main().catch((err) => {
  console.error(err);
  process.exit(1);
});
