"""Soaks and benchmarks that drive a whole node graph: fuzzing, the breaker soak, latency and the WAN."""
