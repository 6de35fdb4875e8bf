"""The ROS plumbing every psl node and client shares: node main, hot-path wait loop, action
client, waiting on futures, QoS profiles, topic names, stamps, the bag writer and one client for
the graph's services and actions. Holds no robotics and no learning."""
