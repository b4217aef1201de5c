"""What render_torso.py and render_bars.py share: the validation set's light transport
and the truth grid's axis description that score.py reads."""

# Third bounce only (relay -> hidden -> relay): max_depth 3, hidden-geometry sampling
# without the relay, direct relay -> laser-spot paths discarded, first and last legs
# not counted, a box filter in time.
INTEGRATOR = {
    "type": "transient_nlos_path",
    "block_size": 1,
    "max_depth": 3,
    "filter_bounces": -1,
    "discard_direct_paths": True,
    "nlos_laser_sampling": True,
    "nlos_hidden_geometry_sampling": True,
    "nlos_hidden_geometry_sampling_do_rroulette": False,
    "nlos_hidden_geometry_sampling_includes_relay_wall": False,
    "temporal_filter": "box",
    "account_first_and_last_bounces": False,
}


def axis(lo, hi, k):
    """One axis of a truth.json `recommended_volume`: k cells over [lo, hi]."""
    step = (hi - lo) / k
    return {"min_center": lo + step / 2, "max_center": hi - step / 2, "n": k, "step": step, "bounds": [lo, hi]}
