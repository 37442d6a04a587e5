"""Finding the physics the model leaves out: locate, explain, correct."""
