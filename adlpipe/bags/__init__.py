"""Reading and writing ROS bags: ROS2 MCAP, ROS1 .bag and ROS2 sqlite3 (.db3), with the real writers/readers."""
