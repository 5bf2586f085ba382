"""What may move a breaker, without rclpy: actuation rules, the audit log, signatures, the known topology."""
