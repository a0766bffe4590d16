"""The web HMI (docs/web.md): `geo-server run --http 127.0.0.1:8080`."""
