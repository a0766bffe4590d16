// geo-server web HMI, the fleet's page (docs/web.md): every machine, a link to its HMI.
"use strict";

const cell = (text) => { const td = document.createElement("td"); td.textContent = text; return td; };

function show(fleet) {
  const body = document.querySelector("#machines tbody");
  body.replaceChildren();
  for (const m of fleet.machines) {
    const tr = document.createElement("tr");
    tr.dataset.machine = m.name;
    if (m.stalled) tr.className = "stalled";
    const link = document.createElement("a");
    link.href = `m/${encodeURIComponent(m.name)}/`;
    link.textContent = m.name;
    const name = document.createElement("td");
    name.append(link);
    tr.append(name, cell(m.cycle), cell(m.engine), cell(m.overruns), cell(m.stalled ? "STALLED" : "no"),
      cell(m.netid), cell(m.modbus_port ?? "–"));
    body.append(tr);
  }
  const machines = fleet.count === 1 ? "1 machine" : `${fleet.count} machines`;
  document.querySelector("#fleet").textContent = `fleet of ${machines}`;
  document.querySelector("#status").textContent =
    `${machines} · overruns ${fleet.overruns} · stalled ${fleet.stalled.length}`;
}

async function refresh() {
  try {
    show(await (await fetch("api/fleet")).json());
  } catch (e) {
    document.querySelector("#status").textContent = `no answer from the server (${e})`;
  }
  setTimeout(refresh, 1000);
}

refresh();
