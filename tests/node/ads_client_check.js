// An unmodified ads-client (npm, version 2) in its default settings against geo-server:
// connect (port connect 0x1000, system state on port 10000, 0xF100 and 0xF008 subscriptions,
// device info, upload info, symbol version), readRaw, readValue / writeValue by symbol,
// subscribe. Prints one JSON line with what it saw; tests/test_ads_node.py checks it.
// Usage: node ads_client_check.js <router TCP port>
const { Client } = require("ads-client");

async function main() {
  const port = Number(process.argv[2]);
  const client = new Client({
    targetAmsNetId: "127.0.0.1.1.1",
    targetAdsPort: 551,
    routerAddress: "127.0.0.1",
    routerTcpPort: port,
  });
  const out = {};
  const conn = await client.connect();
  out.connection = conn;
  out.uploadInfo = client.metaData.plcUploadInfo;
  out.symbolVersion = client.metaData.plcSymbolVersion;
  out.deviceInfo = client.metaData.deviceInfo;
  const ext = await client.readTcSystemExtendedState();
  out.extendedState = { adsState: ext.adsStateStr, restartIndex: ext.restartIndex };
  const raw = await client.readRaw(0x120300, (1 << 16) | 0x43, 8);
  out.readRaw = raw.readDoubleLE(0);
  out.readValue = (await client.readValue("GEO.X.TEMPC.coefficient")).value;
  out.readBool = (await client.readValue("GEO.X.TEMPC.activated")).value;
  out.readString = (await client.readValue("GEO.SIM.axis_names")).value;
  await client.writeValue("GEO.X.TEMPC.offset_0", 77);
  out.afterWrite = (await client.readValue("GEO.X.TEMPC.offset_0")).value;
  try {
    await client.writeValue("GEO.X.TEMPC.coefficient", Infinity);
    out.badWrite = "accepted";
  } catch (err) {
    out.badWrite = err.adsError ? err.adsError.errorCode : String(err);
  }
  try {
    await client.writeValue("GEO.X.TEMPC.coefficient", 20000);
  } catch (err) {
    // the refusal's text, as TwinCAT's clients decode a STRING (Windows-1252)
    out.lastError = (await client.readValue("GEO.SIM.last_error")).value;
  }
  const handle = await client.createVariableHandle("GEO.Y.TEMPC.coefficient");
  out.handle = { size: handle.size, dataType: handle.dataType };
  await client.writeRawByHandle(handle, Buffer.from(new Float64Array([12.5]).buffer));
  out.readByHandle = (await client.readRawByHandle(handle)).readDoubleLE(0);
  await client.deleteVariableHandle(handle);
  const multi = await client.createVariableHandleMulti(["GEO.Z.LSEC.sum_epsilon", "GEO.NO.such"]);
  out.multi = multi.map((r) => (r.success ? r.handle.dataType : r.errorCode));
  await client.deleteVariableHandleMulti([multi[0].handle]);
  try {
    await client.readValue("GEO.X.NO.such");
    out.unknown = "found";
  } catch (err) {
    out.unknown = err.adsError ? err.adsError.errorCode : String(err);
  }
  out.samples = await new Promise((resolve, reject) => {
    const seen = [];
    const timer = setTimeout(() => reject(new Error("no notification in 5 s")), 5000);
    client
      .subscribeValue("GEO.SIM.cycle_count", (data, sub) => {
        // samples of cycles computed together arrive together: keep the first three
        if (seen.length >= 3) return;
        seen.push(data.value);
        if (seen.length === 3) {
          clearTimeout(timer);
          sub.unsubscribe().then(() => resolve(seen), reject);
        }
      }, 10)
      .catch(reject);
  });
  await client.disconnect();
  console.log(JSON.stringify(out));
}

main().catch((err) => {
  console.error(err && err.stack ? err.stack : err);
  process.exit(1);
});
