"""The Zenoh interface: the key space (`keys`, pure functions), its options (`options`),
the server (`server`) and its plug (`plug`). Nothing is imported here: the plug is read
for every command, and loads Zenoh only when it serves."""
