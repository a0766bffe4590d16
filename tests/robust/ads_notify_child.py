"""A pyads client that registers ADS notifications and never deletes them: it prints
`ready` and waits to be killed (SIGKILL: AdsLib gets no chance to clean up).

    python ads_notify_child.py <port> <netid> <count>
"""

from __future__ import annotations

import sys
import time

import pyads

port, netid, count = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
conn = pyads.Connection(netid, 551, f"127.0.0.1:{port}")
conn.open()
conn.set_timeout(5000)
for i in range(count):
    axis = i % 4 + 1
    conn.add_device_notification(
        (0x120300, (axis << 16) | 0x42), pyads.NotificationAttrib(4), lambda *_a: None
    )
print("ready", flush=True)
time.sleep(60)  # killed long before
