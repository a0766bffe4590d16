"""ADS over AMS/TCP (docs/design.md §9): sans-I/O codec, notification table, asyncio server.

server = AdsServer(service, AdsOptions(host="127.0.0.1", port=48898))
await server.start()      # server.port is the bound port (port=0: ephemeral)
...
await server.close()
"""
