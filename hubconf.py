"""torch.hub entry points: the shipped models without this project's package layout.

    import torch
    model = torch.hub.load("<owner>/<repo>", "ev_mgrflownet", pretrained=True)        # from GitHub
    model = torch.hub.load("path/to/checkout", "ev_mgrflownet", source="local", pretrained=True)
    flows, state = model(x, None)   # x: (B, C, H, W) float32; flows: finest last, (B, 2, H, W) pixels
    flows, bounds = torch.hub.load("path/to/checkout", "flow", events, (480, 640), source="local")  # from events

``ev_mgrflownet(pretrained=True, name=None)`` loads the committed weights of a shipped model
(``agents/weights/NAME.pt``; ``name=None``: the project's default, ``agents.pretrained.DEFAULT_PRETRAINED``);
nothing is downloaded beyond the repository itself. The model reads the observation its
``model.provenance["input"]`` names ("count_image": (B, 2, H, W) ON / OFF counts, or
"voxel_grid": (B, voxel_bins, H, W)); ``agents.policy.RecurrentPolicy.from_pretrained(name)``
wraps it with that input and the recurrent state. ``pretrained=False`` builds it untrained.

The published baselines, untrained (no weights are shipped for them): ``ev_flownet`` (Zhu et al.,
4-channel counts and timestamps by default), ``convgru_ev_flownet`` and ``xlif_ev_flownet``
(Hagenaars et al.). Every entry point takes ``width`` ("cpu", "paper" or an integer base width)
and the model's keyword arguments (``agents/registry.py``).
"""

dependencies = ["torch", "numpy", "h5py", "gymnasium", "tqdm", "numba"]


def _untrained(model: str, width, kwargs: dict):
    from agents.registry import make_model, width_kwargs

    return make_model(model, **width_kwargs(width), **kwargs).eval()


def ev_mgrflownet(pretrained: bool = True, name: str | None = None, width: str | int = "cpu", map_location="cpu",
                  **kwargs):
    """EV-MGRFlowNet (Zhuang et al. 2024). pretrained: the shipped weights ``name`` (None: the
    default model; ``agents.pretrained.list_pretrained()`` lists them), in eval mode, with
    ``model.provenance`` (training command, data, metrics, input); else untrained at ``width``."""
    if not pretrained:
        if name is not None:
            raise ValueError(f"name={name!r} names shipped weights; pass pretrained=True to load them")
        return _untrained("ev-mgrflownet", width, kwargs)
    from agents.pretrained import load_pretrained

    if kwargs:
        raise ValueError(f"a pretrained model is built as it was trained; drop {sorted(kwargs)} "
                         "or pass pretrained=False")
    model, info = load_pretrained(name, map_location=map_location)
    model.provenance = info
    return model


def flow(events, sensor_size=None, window_us: int = 33_333, finish: bool = True, device: str = "cpu",
         max_windows: int | None = None):
    """Flow straight from events, the input built for you (no voxel grid to know about):

        flows, bounds = torch.hub.load("path/to/checkout", "flow", events, (480, 640), source="local")

    events: a structured numpy array with fields x, y, t (µs), p (tonic's layout), a dict of those
    four arrays, or a recording's path; sensor_size: (height, width) (tonic's (width, height,
    polarities) too). Returns ((K, 2, H, W) float32 pixels of displacement per ``window_us``
    window, (K, 2) int64 µs window bounds), from the default model in its mode: the network's
    proposal finished by a short solve on each window's events (``finish=False``: the proposal
    alone). ``agents.predict_flow`` is the same function."""
    from agents.inference import predict_flow

    return predict_flow(events, sensor_size, window_us=window_us, finish=finish, device=device,
                        max_windows=max_windows)


def _baseline(model: str):
    def entry(pretrained: bool = False, width: str | int = "cpu", **kwargs):
        if pretrained:
            raise ValueError(f"no weights are shipped for {model}; pass pretrained=False for the untrained network "
                             "(train it with scripts/train.py --model " + model + ")")
        return _untrained(model, width, kwargs)

    entry.__name__ = model.replace("-", "_")
    entry.__doc__ = f"The {model} baseline (agents/baselines.py), untrained (no shipped weights)."
    return entry


ev_flownet = _baseline("ev-flownet")
convgru_ev_flownet = _baseline("convgru-ev-flownet")
xlif_ev_flownet = _baseline("xlif-ev-flownet")
