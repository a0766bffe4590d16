"""The web HMI (docs/web.md): `geo-server run --http 127.0.0.1:8080`."""

#: Debian's Chromium, which the browser tests and the screenshot script drive with
#: Playwright (never a browser Playwright downloads; docs/web.md §5)
CHROMIUM = "/usr/bin/chromium"
#: flags for a headless Chromium as root on a host without internet: without the
#: background-networking ones it keeps trying to reach Google's hosts
CHROMIUM_ARGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)
