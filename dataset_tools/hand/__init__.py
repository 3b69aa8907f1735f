"""The 26-DOF hand: skeleton and forward kinematics, bone lengths, inverse kinematics."""
