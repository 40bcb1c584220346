"""What the thesis's ground robots share (sec. 4.2.2: the snake-like robot, the pivotboard): not a
scenario kind itself.

* :mod:`.plane`: the ground plane, tilted about the world y axis, and its frame;
* :mod:`.config`: what every ground robot's scenario has (rates, settling, commands), and the
  reading of a phase map's file;
* :mod:`.sweep`: what their sweeps share (a grid of jobs in processes, the commit);
* :mod:`.phase_sweep`: eq. 4.1's search (the argmax on a wrapping phase grid, the map unwrapped);
* :mod:`.control`: what their motion control shares (the period velocity, the line-holding law,
  the CPG's period clock);
* :mod:`.run`: the loop (MuJoCo at the physics step, the CPG at its rate setting the servos'
  targets, the log), the body frame's velocities averaged over a CPG period, the metrics per
  command and the path plot.
"""
