"""Test configuration: float64 everywhere, as the CLI sets it at its entry point."""

import jax

jax.config.update("jax_enable_x64", True)
