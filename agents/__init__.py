"""Flow networks (pure ``forward(x, state) -> (flows, state)`` modules), the model registry and
the stateful policy wrapper. See ``agents/protocol.py`` for the protocol and
``agents/registry.py`` for how to bring your own model."""

from .baselines import ConvGRUEVFlowNet, EVFlowNet, UNetConvGRU, UNetFeedforward, UNetXLIFEncoder, XLIFEVFlowNet
from .evmgrflownet import EVMGRFlowNet
from .flownet import WIDTHS
from .inference import predict_flow
from .policy import RecurrentPolicy
from .protocol import ModelLoadError, ProtocolError, check_protocol
from .registry import MODELS, make_model, register_model

__all__ = [
    "predict_flow",
    "MODELS",
    "WIDTHS",
    "ConvGRUEVFlowNet",
    "EVFlowNet",
    "EVMGRFlowNet",
    "ModelLoadError",
    "ProtocolError",
    "RecurrentPolicy",
    "UNetConvGRU",
    "UNetFeedforward",
    "UNetXLIFEncoder",
    "XLIFEVFlowNet",
    "check_protocol",
    "make_model",
    "register_model",
]
