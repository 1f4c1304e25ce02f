"""Live mapping on a ROS 2 robot over Zenoh, with no ROS install (docs/robot.md): ``evsemmap live`` subscribes
to the robot's LiDAR and TF, maps scan by scan as the log source does and publishes the map back;
``evsemmap replay`` publishes a recorded log as the robot would. Needs the ``live`` extra (eclipse-zenoh).

One job per module: ``ros2_wire`` (keys, attachments, liveliness tokens, message types), ``session``
(opening a Zenoh session), ``node`` (publishing as a ROS 2 node), ``scan_queue`` (the bounded queue),
``feed`` (the subscriptions), ``mapping`` (the mapping loop), ``publish`` (map, layers, diagnostics),
``replay`` and ``commands`` (the command line)."""
