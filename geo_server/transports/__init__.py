"""The three interfaces of a machine — `zenoh`, `modbus`, `ads` — each a sans-I/O codec
beside a thin asyncio server over the object service (`geo_server.service`). They import
only the service, the shared types (`snapshot`, `events`, `errors`) and the dictionary."""
