"""Independent validation rigs: simulators written apart from :mod:`ewb_ident`.

Each module simulates an electronic wedge brake rig with code of its own, so that the
tool is checked on recordings it was not developed against. The tests, studies and
benchmarks import them from here (``from validation_rigs import other_rig``).

* :mod:`validation_rigs.other_rig`: "somebody else's rig", the seed chain with wide
  parameter ranges and a SciPy motor (tests, convergence and compare studies).
* :mod:`validation_rigs.third_rig`: a third rig written by a separate author from the
  trace format and the seed model only (``python -m validation_rigs.third_rig``).
* :mod:`validation_rigs.uncatalogued_rig`: physics that is in no catalog, for the
  discovery study (``python -m validation_rigs.uncatalogued_rig``).

The package is installed beside ``ewb_ident`` (``pyproject.toml``'s package discovery)
but is no part of the tool: ``ewb_ident`` never imports it.
"""
