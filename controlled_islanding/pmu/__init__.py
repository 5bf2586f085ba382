"""PMU streams without rclpy: IEEE C37.118.2 frames, the PDC end of a stream, a bag served as a PMU."""
