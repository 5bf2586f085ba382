"""What travels and is stored, as plain data without rclpy: message types and checks, topics, QoS, time, bags."""
