"""How `geo-server run` sets up its OPC UA interface, for one machine and for a fleet
(README *OPC UA*, docs/security.md *OPC UA*): the options from the command line, where
the server's certificate is kept, and what is said when the background start ends."""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from geo_server.interfaces import start_failure
from geo_server.paths import default_startup_list, is_product_data
from geo_server.transports.opcua.server import OpcUaOptions

if TYPE_CHECKING:  # built by the composition root only (geo_server/compose.py)
    from geo_server.transports.opcua.server import OpcUaInterface


def user_folder() -> Path:
    """The user's geo-server folder (for the shipped default machine's certificate)."""
    if sys.platform == "win32":
        base = Path(os.environ.get("APPDATA") or Path.home() / "AppData" / "Roaming")
    else:
        base = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config")
    return base / "geo-server"


def cert_folder(startup: Path) -> Path:
    """`opcua/` beside the start-up list, or in `user_folder` for the shipped machine."""
    if is_product_data(startup):
        return user_folder() / "opcua"
    return Path(startup).resolve().parent / "opcua"


def announce(iface: OpcUaInterface, where: str) -> None:
    """`geo-server run`: say when the background start is done, or why it failed."""

    def said(exc: BaseException | None) -> None:
        if exc is None:
            print(f"opcua: ready on {iface.endpoint} ({where})", flush=True)
            return
        text = start_failure("opcua", exc)
        print(f"error: {text} (the other interfaces keep serving)", file=sys.stderr, flush=True)

    iface.on_started = said


def options_from_args(args: Any, startup: Path | None, caps: Mapping[str, int]) -> OpcUaOptions:
    """The options of `geo-server run` (one machine or a fleet; `startup`: the start-up
    list or fleet file the certificate is kept beside, `cert_folder`)."""
    folder = args.opcua_cert_dir
    opts = OpcUaOptions(
        endpoint=args.opcua_endpoint,
        read_only=args.read_only or args.opcua_read_only,
        user=args.opcua_user,
        password=args.opcua_password,
        cert_dir=Path(folder) if folder else cert_folder(startup or default_startup_list()),
        encrypt_only=args.opcua_encrypt_only,
        companion_models=not args.opcua_no_companions,
        background=True,
    )
    if "opcua" in caps:
        opts.shrink_to(caps["opcua"])
    return opts


__all__ = ["announce", "cert_folder", "options_from_args", "user_folder"]
