"""ROS 2 interface of the vendor sample, spoken over DDS (work in progress, issue 6).

So far: the vendor-compatible interface package (``interface/abh3_can_interface``: the
``.msg``/``.srv`` files, to build with colcon for your own nodes), the DDS types ROS 2
uses on the wire for them (:mod:`.types`), checked byte for byte against an independent
CDR implementation, and the read-only bridge plugin (:mod:`.bridge`). Commands from ROS 2
(``vel_cmd``, ``cur_cmd``, ``inp_data``, ``inp_service``, ``cmd_vel``) come next.
"""
