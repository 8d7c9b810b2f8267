"""The simulation study beside the product: DIRL against imitation learning on carrt's simulator.

Not part of the installed package (pyproject's packages.find leaves it out): the experiments, their
engine, the study log and the results behind each claim (research/README.md). It imports carrt,
training and bench.provenance; nothing in the product imports it."""
