"""Pure numerical core of fdi_ros. Nothing below this package imports rclpy."""
