"""Motion generation on the leader (thesis ch. 4): pure numpy, no I/O or clocks."""
