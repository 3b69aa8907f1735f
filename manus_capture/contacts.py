"""Hand-object contact from Gaussians: nearest neighbours between the posed hand and the object.

MANUS defines contact on the Gaussians themselves: a hand Gaussian touches the object when the
nearest object Gaussian is closer than tau (4 mm), and the reverse gives the contact on the
object. Over a take the instantaneous maps (T,G) accumulate by maximum into one map (G,) per
hand Gaussian, which is what the paint on the subject's hand records.

Anything with `pose(angles) -> {"means", "covars"}` and `pose_batch(angles) -> means` is a hand
model here: the trained MANUS-Hand (splat.hand.HandGaussians) and the capsule template of the
baseline (template.capsule_template) are scored by the same code.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from scipy.spatial import cKDTree

from manus_core.dataset import add_arrays

from .splat.rasterize import rasterize
from .torch_threads import torch_threads

TAU_M = 0.004
# Contact is drawn on the skin, which is opaque: every Gaussian is splatted this opaque, whatever
# opacity it learned for the photographs. With the learned opacities a surfel of 0.4 on the
# palmar side let the back of the finger behind it show through, and the paint's label was
# diluted below the threshold (docs/contacts.md, "Rendering contact").
SURFACE_OPACITY = 0.99
CHUNK = 1 << 12  # hand points per torch.cdist block on the GPU: 4096 x M distances at a time
# Frames posed per call. MKL's matrix product adds up a posed point in an order that depends on
# how many frames are in the call and on the thread count (3e-8 m apart, measured), so frames are
# posed in calls of this many, counted from the take's first frame, on one thread: a frame's
# points are then the same whichever task of a split take (contact_tasks.py) or process poses it.
# One thread is as fast here as eight.
POSE_FRAMES = 32


class PosedModel(Protocol):
    """A hand model the contact and rendering code can pose."""

    def pose(self, angles: torch.Tensor) -> dict[str, torch.Tensor]: ...

    def pose_batch(self, angles: torch.Tensor) -> torch.Tensor: ...


@dataclass(frozen=True)
class ContactMaps:
    """Contact values in [0,1]: hand `instant` (T,G), `accumulated` (G,) and the same for the
    object (`object_instant` (T,M), `object_accumulated` (M,))."""

    instant: np.ndarray
    accumulated: np.ndarray
    object_instant: np.ndarray
    object_accumulated: np.ndarray
    tau: float
    soft: bool


def contact_value(distance: np.ndarray, tau: float = TAU_M, soft: bool = False) -> np.ndarray:
    """1 below tau (binary) or 1 - d/tau clipped to [0,1] (soft); 0 at or beyond tau."""
    d = np.asarray(distance, dtype=np.float64)
    if soft:
        return np.clip(1.0 - d / tau, 0.0, 1.0).astype(np.float32)
    return (d < tau).astype(np.float32)


def _cpu_pairs(hand: np.ndarray, obj: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (hand index, object index, distance) pairs closer than tau, through two KD-trees."""
    pairs = cKDTree(hand).sparse_distance_matrix(cKDTree(obj), tau, output_type="ndarray")
    return pairs["i"].astype(np.int64), pairs["j"].astype(np.int64), pairs["v"]


def _cuda_pairs(hand: np.ndarray, obj: np.ndarray, tau: float, device: str):
    """The same pairs from chunked torch.cdist on the GPU (no tree; the M object points stay resident)."""
    o = torch.as_tensor(obj, dtype=torch.float32, device=device)
    hi, oi, dist = [], [], []
    for start in range(0, len(hand), CHUNK):
        h = torch.as_tensor(hand[start:start + CHUNK], dtype=torch.float32, device=device)
        d = torch.cdist(h, o)
        i, j = torch.nonzero(d < tau, as_tuple=True)
        hi.append((i + start).cpu())
        oi.append(j.cpu())
        dist.append(d[i, j].double().cpu())
    return torch.cat(hi).numpy(), torch.cat(oi).numpy(), torch.cat(dist).numpy()


def hand_object_contacts(model: PosedModel, angles: np.ndarray, object_means: np.ndarray, tau: float = TAU_M,
                         soft: bool = False, device: str = "cpu") -> ContactMaps:
    """Contact maps of a hand model posed by `angles` (T,26) against static object points (M,3):
    each posed hand point's nearest object point, and the reverse, contact below tau.

    All frames go through one neighbour search, the hand's T*G posed points against the object,
    so the object's per-frame map comes from the same pairs.
    """
    if tau <= 0:
        raise ValueError(f"tau must be positive, got {tau}")
    angles = np.atleast_2d(np.asarray(angles, dtype=np.float64))
    finite = np.all(np.isfinite(angles), axis=1)
    means = _posed_means(model, np.where(finite[:, None], angles, 0.0))
    T, G = means.shape[:2]
    object_means = np.asarray(object_means, dtype=np.float64)
    hand_flat = means.reshape(-1, 3)
    if str(device).startswith("cuda"):
        i, j, v = _cuda_pairs(hand_flat, object_means, tau, device)
    else:
        i, j, v = _cpu_pairs(hand_flat, object_means, tau)
    # frames without a fitted hand have no contact, not the rest pose's
    keep = finite[i // G]
    i, j, v = i[keep], j[keep], v[keep]
    distance = np.full(T * G, np.inf)
    np.minimum.at(distance, i, v)
    distance = distance.reshape(T, G)
    obj_distance = np.full((T, len(object_means)), np.inf)
    np.minimum.at(obj_distance, (i // G, j), v)
    return accumulate(contact_value(distance, tau, soft), contact_value(obj_distance, tau, soft), tau, soft)


def accumulate(instant: np.ndarray, object_instant: np.ndarray, tau: float, soft: bool) -> ContactMaps:
    """The maps of instantaneous contact (T,G) and (T,M): accumulated by maximum over the frames."""
    return ContactMaps(instant, instant.max(axis=0, initial=0.0), object_instant,
                       object_instant.max(axis=0, initial=0.0), tau, soft)


def _posed_means(model: PosedModel, angles: np.ndarray) -> np.ndarray:
    """Posed hand points (T,G,3) of finite angles (T,26), POSE_FRAMES frames a call, one thread."""
    with torch.no_grad(), torch_threads(1):
        # one call even for no frames: its (0,G,3) keeps the shapes of an empty take
        return np.concatenate([model.pose_batch(torch.as_tensor(angles[s:s + POSE_FRAMES], dtype=torch.float32))
                               .cpu().numpy() for s in range(0, max(len(angles), 1), POSE_FRAMES)])


def model_contacts(hand, angles: np.ndarray, obj, tau: float = TAU_M, soft: bool = False,
                   device: str = "cpu") -> ContactMaps:
    """hand_object_contacts of a hand model against object Gaussians (splat.gaussians.Gaussians)."""
    return hand_object_contacts(hand, angles, obj.means.detach().cpu().numpy(), tau, soft, device)


def render_values(model: PosedModel, angles: np.ndarray, values: np.ndarray, viewmats: torch.Tensor,
                  Ks: torch.Tensor, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Splat a per-Gaussian value (G,) as colour of the posed hand, every Gaussian SURFACE_OPACITY
    opaque, into C cameras: (composited value (C,H,W), premultiplied by alpha as rasterize()
    returns it, and alpha (C,H,W)). The value of the visible surface is their ratio where
    alpha > 0 (surface_value)."""
    with torch.no_grad():
        posed = model.pose(torch.as_tensor(np.asarray(angles, dtype=np.float32)))
        means = posed["means"]
        colours = torch.as_tensor(np.asarray(values), dtype=means.dtype, device=means.device)[:, None]
        opacities = torch.full((len(means),), SURFACE_OPACITY, dtype=means.dtype, device=means.device)
        out, alpha = rasterize(means, None, None, opacities, colours, viewmats, Ks, width, height,
                               covars=posed["covars"])
    return out[..., 0].cpu().numpy(), alpha[..., 0].cpu().numpy()


def surface_value(premultiplied: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """The value of the visible surface: premultiplied value over alpha, 0 where nothing is drawn."""
    return np.where(alpha > 1e-3, premultiplied / np.maximum(alpha, 1e-3), 0.0).astype(np.float32)


def contact_image(value: np.ndarray, alpha: np.ndarray, image: np.ndarray | None = None) -> np.ndarray:
    """A BGR uint8 picture of a rendered contact map: the hand in grey, contact from yellow to red,
    over `image` (H,W,3 BGR) when given."""
    value = np.clip(value, 0.0, 1.0)[..., None]
    grey = np.array([170.0, 170.0, 170.0])
    hot = np.stack([np.zeros_like(value[..., 0]), 220.0 * (1.0 - value[..., 0]), np.full_like(value[..., 0], 255.0)],
                   axis=-1)
    hand = np.where(value > 0.0, hot, grey)
    base = np.zeros(value.shape[:2] + (3,)) if image is None else image.astype(np.float64)
    a = alpha[..., None]
    return np.clip(base * (1.0 - a) + hand * a, 0, 255).astype(np.uint8)


def write_contacts(path, key: str, maps: ContactMaps, attrs: dict) -> None:
    """Store a take's contact maps in DATASET.h5 (group `key`/contacts, compressed), atomically;
    instantaneous maps already in float16 (a contact_tasks.ContactStore's, arrays or HDF5
    datasets) are copied as they are."""
    add_arrays(path, key, {"contacts/instant": _float16(maps.instant),
                           "contacts/accumulated": maps.accumulated,
                           "contacts/object_instant": _float16(maps.object_instant),
                           "contacts/object_accumulated": maps.object_accumulated},
               {"contact_tau_m": maps.tau, "contact_soft": maps.soft, **attrs}, stage="contacts")


def _float16(maps: np.ndarray) -> np.ndarray:
    return maps if maps.dtype == np.float16 else maps.astype(np.float16)
