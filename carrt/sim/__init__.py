"""The built-in simulator (numpy only): the paper's fenced arena, a 1/20-scale car, its camera,
a scripted expert and the paper's metrics. The stand-in for the car wherever none is attached."""
