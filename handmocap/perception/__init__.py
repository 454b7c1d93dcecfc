"""Hand perception: finder, detector, tracker, pose, shape, translation, IK, kinematics, hand model."""
