"""One error vocabulary for the whole project.

- `GeoError` is the base of every exception geo-server raises on purpose; a caller that
  wants "anything this library refused" catches it.
- `AdsError` carries an ADS return code (`AdsErrorCode`) and a precise message. The
  object service raises it for every refusal, and each transport maps the code to its
  own (Modbus exception, Zenoh `reply_err` body, ADS response) — so the codes below are
  the common language of the interfaces (docs/design.md §9 lists what each means here).
- `CncErrorId` names the error IDs of the CNC (P-ERR-…) that the machine reports in its
  error list, as the manuals number them.
"""

from __future__ import annotations

from enum import IntEnum
from typing import Any


class GeoError(Exception):
    """Base of the exceptions geo-server raises on purpose."""


class AdsErrorCode(IntEnum):
    """ADS/AMS return codes geo-server produces (Beckhoff AdsDef.h names, without the
    `ADSERR_` prefix)."""

    NOERROR = 0x000
    TARGET_PORT_NOT_FOUND = 0x006
    TARGET_MACHINE_NOT_FOUND = 0x007
    INVALID_AMS_LENGTH = 0x00E
    DEVICE_ERROR = 0x700  # general device error (a defect: the message says what)
    DEVICE_SRVNOTSUPP = 0x701  # service / command not supported
    DEVICE_INVALIDGRP = 0x702  # unknown index group
    DEVICE_INVALIDOFFSET = 0x703  # unknown index offset, object or axis
    DEVICE_INVALIDACCESS = 0x704  # read-only / write-only, interface read-only
    DEVICE_INVALIDSIZE = 0x705  # wrong length
    DEVICE_INVALIDDATA = 0x706  # value of the wrong type or out of range
    DEVICE_NOTREADY = 0x707  # the GEO cycle is stalled or ended
    DEVICE_BUSY = 0x708  # axis busy, program running, another command running
    DEVICE_INVALIDPARM = 0x70B  # parameter values not valid (a fault that cannot be injected)
    DEVICE_SYNTAX = 0x70D  # list file or NC text has errors (reload rejected)
    DEVICE_SYMBOLNOTFOUND = 0x710  # unknown symbol name or handle
    DEVICE_INVALIDSTATE = 0x712  # the device cannot go to the requested ADS state
    DEVICE_TRANSMODENOTSUPP = 0x713
    DEVICE_NOTIFYHNDINVALID = 0x714
    DEVICE_NOMOREHDLS = 0x716  # notification or symbol handle limit reached
    DEVICE_INVALIDWATCHSIZE = 0x717
    DEVICE_TIMEOUT = 0x719  # not applied in time: withdrawn, it will not take effect


class AdsError(GeoError):
    """A request failed with an ADS return code; `message` says precisely why."""

    def __init__(self, code: int, message: str, name: str = "") -> None:
        super().__init__(f"ADS error 0x{code:X}: {message}")
        self.code = int(code)
        self.message = message
        self.name = name

    def __reduce__(self) -> tuple[Any, ...]:
        # pickles across the process boundary of the GEO cycle with its fields intact
        return (type(self), (self.code, self.message, self.name))

    def as_dict(self) -> dict[str, Any]:
        """The JSON error body of the Zenoh interface."""
        return {"ads_error": self.code, "name": self.name, "message": self.message}


class CncErrorId(IntEnum):
    """CNC error IDs the machine reports (000 §5, p.73 and p.97)."""

    #: P-ERR-70435: an axis moved in automatic mode without the compensations
    #: `lr_param.prog_movement_requires_compensations` requires (000 §5.3, p.97).
    REQUIRED_COMP_MISSING = 70435
    #: P-ERR-70495: `COMP ON FRICT` while `lr_param.frict_comp` is not set (000 p.73).
    FRICT_NOT_SELECTED = 70495


__all__ = ["AdsError", "AdsErrorCode", "CncErrorId", "GeoError"]
