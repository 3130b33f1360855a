"""FluidLab's ROS side: the pure-Python execution pipeline (`fluidlab_ros.pipeline.plan`) and, later, the
rclpy nodes. Importing this package does not import rclpy or Taichi."""
