"""Bag input/output without ROS (the ``rosbags`` library only): ``reader`` opens ROS 1 and
rosbag2 (sqlite3, MCAP) bags, ``writer`` writes rosbag2 bags and builds their messages, ``tf``
reads /tf and /tf_static (odometry from odom → base_link, the laser's mount)."""
from __future__ import annotations

from localization.bags.reader import (
                                      DEFAULT_TYPESTORE,
                                      ROS2_BAG_SUFFIXES,
                                      BagError,
                                      BagInfo,
                                      BagMessage,
                                      BagReader,
                                      TopicInfo,
                                      bag_info,
                                      jazzy_typestore,
                                      open_bag,
                                      read_messages,
                                      topics,
)
from localization.bags.tf import LaserMount, laser_mount_from_bag, odometry_from_tf, read_tf
from localization.bags.writer import (
                                      LATCHED_QOS,
                                      RELIABLE_QOS,
                                      BagWriter,
                                      make_header,
                                      make_laser_scan,
                                      make_odometry,
                                      make_pose,
                                      make_tf_message,
                                      make_time,
                                      make_transform_stamped,
                                      stamp_to_ns,
)

__all__ = ["BagError", "BagInfo", "BagMessage", "BagReader", "BagWriter", "DEFAULT_TYPESTORE", "LATCHED_QOS",
           "LaserMount", "laser_mount_from_bag", "odometry_from_tf", "read_tf",
           "RELIABLE_QOS", "ROS2_BAG_SUFFIXES", "TopicInfo", "bag_info", "jazzy_typestore", "make_header",
           "make_laser_scan", "make_odometry", "make_pose", "make_tf_message", "make_time", "make_transform_stamped",
           "open_bag", "read_messages", "stamp_to_ns", "topics"]
