"""What OPC UA puts in a machine's status, named once: the server and OPC UA's own
process write these entries, the plug reads them for a fleet's status
(`Interface.fleet_counts`). Imports nothing: the plug is loaded for every command."""

from __future__ import annotations

#: its share of OPC UA's processor time (`LoopShare.status`, a fleet's machines)
SHARE_STATUS = "opcua_share"
#: its monitored items' sampling (`Monitoring.counts`)
ITEMS_STATUS = "opcua_items"
#: the only entries OPC UA's own process may set (`apart._shown`)
STATUS_KEYS = (SHARE_STATUS, ITEMS_STATUS)
