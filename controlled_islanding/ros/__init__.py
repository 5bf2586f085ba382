"""The rclpy runtime every node shares: the process, diagnostics, parameters and limits, intake, waiting requests."""
