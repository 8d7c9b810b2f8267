"""The shared simulator dataset fixture itself: what the training tests rely on."""

from carrt.episodes.reader import list_episodes, read_episode


def test_sim_dataset_has_clean_laps_and_collisions(sim_episodes):
    episodes = [read_episode(p) for p in list_episodes(sim_episodes)]
    assert len(episodes) == 7
    reasons = sorted(ep.end_reason for ep in episodes)
    assert reasons == ["collision"] * 3 + ["disarmed"] * 4
    placements = {(ep.meta["sim"]["layout"], ep.meta["sim"]["track_seed"]) for ep in episodes}
    assert placements == {("easy", 0), ("easy", 1)}
    assert sum(ep.n for ep in episodes) > 150
    crashed = [ep for ep in episodes if ep.end_reason == "collision"]
    assert all(ep.collision[-5:].all() and not ep.collision[0] for ep in crashed)
