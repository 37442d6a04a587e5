"""The seed model: parameters, physics, the motor integrator and the chain evaluator."""
