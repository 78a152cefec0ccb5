"""ROS tools on rclpy and rosbags: `deckland topic`, `deckland bag`, the shared ROS I/O helpers
and deckland_interfaces type registration."""
