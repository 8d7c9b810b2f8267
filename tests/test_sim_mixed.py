"""The "mixed" layout: the paper's varied placements (random positions, colours and numbers)
for training data, while "hard" keeps its fixed 8 obstacles for evaluation."""

from __future__ import annotations

from carrt.sim.expert import ScriptedExpert
from carrt.sim.track import build_track
from carrt.sim.world import SimWorld


def test_mixed_placements_vary_in_number_and_colour_and_hard_stays_fixed():
    mixed = [build_track("mixed", seed) for seed in range(30)]
    counts = {len(t.obstacles) for t in mixed}
    assert min(counts) >= 4 and max(counts) <= 10 and len(counts) >= 5
    colours = [o.colour for t in mixed for o in t.obstacles]
    assert len(set(colours)) > 0.9 * len(colours), "colours are drawn per obstacle"
    assert build_track("mixed", 3) == build_track("mixed", 3), "a seed is a placement"
    assert all(len(build_track("hard", s).obstacles) == 8 for s in range(5))
    assert {o.colour for o in build_track("hard", 0).obstacles} != {
        o.colour for o in build_track("hard", 1).obstacles
    }


def test_the_expert_laps_mixed_placements_cleanly():
    for seed in (0, 5, 11):
        track = build_track("mixed", seed)
        world = SimWorld(track=track)
        expert = ScriptedExpert(track, world.params)
        while world.laps < 1:
            world.step(0.1, *expert.act(world.car))
            assert not world.collided, (seed, world.s)
            assert world.time < 30
