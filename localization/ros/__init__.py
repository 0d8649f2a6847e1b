"""The ROS 2 adapter: the node and what it needs (parameters and QoS, message converters and
builders, stamps, TF broadcaster, the sensor-update thread). Importing this package imports no ROS
module; its modules do (except ``conversions``, which only reads message fields)."""
