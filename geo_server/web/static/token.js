// geo-server web HMI (docs/web.md §4): the run's write token. The server prints the
// page's URL with ?token=…; the page keeps it for this tab (sessionStorage, so a
// machine's page opened from the fleet's has it too), takes it out of the address bar
// (out of the history and of bookmarks) and sends it with every write, reload and save.
"use strict";

const GEO_TOKEN = (() => {
  const url = new URL(location.href);
  const given = url.searchParams.get("token");
  if (given !== null) {
    sessionStorage.setItem("geo-server-token", given);
    url.searchParams.delete("token");
    history.replaceState(history.state, "", url.pathname + url.search + url.hash);
  }
  return sessionStorage.getItem("geo-server-token") || "";
})();

// headers of a POST: a JSON body and the token (the server refuses anything else)
const postHeaders = () => ({ "Content-Type": "application/json", "X-Geo-Token": GEO_TOKEN });
