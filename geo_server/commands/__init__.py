"""Commands as services of their own (docs/design.md §5.7): each module serves one
command over the ports the object service hands it (`ports.Ports`) — reading and
writing list files (`reload`, `save`, `volumetric`; by name through
`lists.CommandService`, the service's `commands`), NC text and reset (`nc`), the ISO
230-2 measurement (`measure`), recordings (`record`) and injected faults (`faults`).
They queue machine operations and wait for them with the service's one
timeout/withdraw rule (`Ports.settle_sync`, `Ports.settle`); one list command runs at a
time (`ports.CommandLock`). The object service builds them once and routes the command
objects (`SIM::reload`, `SIM::save`, `VOLC::file`) to them.
"""
