"""Thin rclpy nodes of fdi_ros, one module per node kind (each also a console script)."""
