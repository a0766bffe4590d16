"""The OPC UA interface (README *OPC UA*): `space.py` the address space planned from the
dictionary (no OPC UA library), `server.py` the thin asyncua server over the object
service, `certs.py` its self-signed certificate, `plug.py` the options of `geo-server run`
(parsed without importing the server)."""
