"""Performance and accuracy: rollouts, SVGD steps, solves, gradients, colliders against C."""
