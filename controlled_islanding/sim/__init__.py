"""The simulated grid: ANDES scenarios, simulated PMUs, bag writing and its manifest, the grid in the loop."""
