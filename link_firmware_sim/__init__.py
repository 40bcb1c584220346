"""The simulated Pixhawk of one link: SE(3) EKF (``ekf``); control and allocation follow."""
