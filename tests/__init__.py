"""The test suite (a package, so that a benchmark can import a test's reference code as
``tests.NAME``)."""
