"""The science of controlled islanding: numpy, scipy and scikit-learn only, never rclpy."""
