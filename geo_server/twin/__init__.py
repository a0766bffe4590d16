"""The machine behind the controller: a digital twin of the axes' errors and temperatures,
and the measurement that proves a compensation on it (docs/twin.md).

- `model`: the twin's parameters (pure data, part of the machine model);
- `file`: the twin file (TOML beside the start-up list), validated with file and line;
- `thermal`: first-order lumped thermal nodes, sensors;
- `engine`: per GEO cycle the true tool position and the residual error, vectorised;
- `iso230`: the ISO 230-2 evaluation of a bidirectional positioning test;
- `measure`: the test itself, run on a machine;
- `plots`: figures (optional, matplotlib).
"""
