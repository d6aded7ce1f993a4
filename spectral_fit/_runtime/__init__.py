"""Process-level support shared by every layer: input errors, atomic file output, the device
layout, compiled calls that return early, process settings (BLAS threads, malloc, CPU devices),
lazy package exports, where the package and its bundled data are."""
