"""
``tube``: a forward model that moves the robot instead of redrawing pixels.

Per view it predicts K keypoints of the robot's backbone (x, y, radius, depth in px), draws
the tube they describe with :mod:`~softshape_ros.model.tube_render` (sharp by
construction: a 1-pixel anti-aliased edge wherever the keypoints put it), and composes it
over the scene with the robot removed, hidden where the object stands in front of it::

    out = a v shade + (1 - a v) background

- **Keypoints** (:class:`KeypointNet`): an MLP of the pressures gives the free shape
  (offsets from a template, the dataset's mean shape); an MLP of the pressures and a scene
  code corrects it where the object is in the way. The code comes from a CNN over the rest
  images alone (:class:`SceneEncoder`), which also reads the object's kind, position and
  size back out of it: trained against the placement where it is known.
- **Background** (:class:`BackgroundNet`): the rest image outside the resting robot's
  tube (the free shape at zero pressure), a small U-Net's fill inside it. Code and
  background depend only on the scene, so inference computes them once per scene (``cache``).
- **Visibility**: a small FiLM CNN over the rest images, the drawn coverage and depth,
  conditioned on the pressures and the scene code: where the object is in front of the
  robot, the object's pixels stay. With ``depth_test`` (:class:`ObjectNet`) instead a depth
  test: a per-scene map of where the object is and how near its front lies, against the
  tube's own near surface.

Trained on the simulator's shape record (``ds.shape``) with keypoint L1 in px, an L1 of
the scene description against the recorded placement (``data.scene_targets``), plus an L1
image loss of the composite (with the predicted keypoints, and with the true ones so the
background, visibility and shading learn from exact shapes) and a masked L1 of the
background where the true robot is not; on recorded bags (no shape record) with the image
loss alone: the renderer is differentiable.

An **ensemble** (``members`` > 1, made by :func:`~softshape_ros.model.ensemble.ensemble`
from separately trained checkpoints) keeps the other trainings' keypoint networks beside
its own and draws the mean of their keypoints with its own renderer: the trainings' misses
on new placements differ, and their mean misses less (docs/model.md, "Trainings averaged").
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from pathlib import Path
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from softshape_ros.model.layers import Stage, coordinate_planes, down_conv, up_conv
from softshape_ros.model.data import SCENE_FEATURES
from softshape_ros.model.tube_render import R, X, Y, TubeField, TubeShader, coverage
from softshape_ros.model.tube_render import front_depth, tube_field

N_PRESSURES = 6
# The depth test's softness (px of depth): where the robot's near surface is this much
# behind the object's, it is hidden by 1 / (1 + e^-1) (docs/model.md, "A depth test").
DEPTH_SOFT_PX = 1.0
KEYPOINTS = 16
# Output scale of the keypoint heads per channel (x, y, radius, depth; px): the MLPs work
# in units of about one.
KEYPOINT_SCALE = (8.0, 8.0, 0.5, 8.0)


class TubeOutput(NamedTuple):
    """Everything one forward pass makes (images B x V*C x S x S, keypoints B x V x K x 4)."""

    image: torch.Tensor
    keypoints: torch.Tensor
    free_keypoints: torch.Tensor
    background: torch.Tensor
    alpha: torch.Tensor             # B x V x S x S: coverage x visibility
    teacher: torch.Tensor | None    # the composite drawn from the true keypoints, if given
    teacher_coverage: torch.Tensor | None   # B x V x S x S: the true keypoints' tube
    teacher_visibility: torch.Tensor | None  # B x V x S x S logits: robot in front there
    scene: torch.Tensor             # B x 17: the object as the scene code describes it
    occupancy: torch.Tensor | None = None     # B x V x S x S logits: the object (depth_test)
    object_depth: torch.Tensor | None = None  # B x V x S x S px: its front (depth_test)


class SceneParts(NamedTuple):
    """What the model makes of the rest images alone (the same for every actuation)."""

    code: torch.Tensor              # B x code
    described: torch.Tensor         # B x 17 SCENE_FEATURES read back from the code
    background: torch.Tensor        # B x VC x S x S: the scene with the robot removed
    # B x 2V x S x S: ObjectNet's occupancy logits, then depths (depth_test; else B x 0)
    objects: torch.Tensor
    # B x (M - 1) code: the other keypoint members' scene codes (an ensemble; else B x 0)
    member_codes: torch.Tensor


def mlp(cin: int, hidden: int, cout: int, zero_last: bool = True) -> nn.Sequential:
    """Return Linear-ReLU-Linear-ReLU-Linear; the last layer zero-initialised by default."""
    net = nn.Sequential(nn.Linear(cin, hidden), nn.ReLU(), nn.Linear(hidden, hidden),
                        nn.ReLU(), nn.Linear(hidden, cout))
    if zero_last:
        nn.init.zeros_(net[-1].weight)
        nn.init.zeros_(net[-1].bias)
    return net


#: True within :func:`scenes_shared`.
_SHARED = contextvars.ContextVar('scenes_shared', default=False)
#: True within :func:`encoder_bf16`.
_BF16 = contextvars.ContextVar('encoder_bf16', default=False)
#: True within :func:`scene_nets_bf16`.
_BF16_NETS = contextvars.ContextVar('scene_nets_bf16', default=False)
#: True within :func:`compiled_renderer`.
_COMPILED = contextvars.ContextVar('compiled_renderer', default=False)


@contextlib.contextmanager
def _set(flag: contextvars.ContextVar, value: bool = True):
    """Give ``flag`` ``value`` within the context, and back its value after it."""
    token = flag.set(value)
    try:
        yield
    finally:
        flag.reset(token)


def scenes_shared():
    """
    Within it, :func:`per_scene` runs once per distinct rest image without gradients too.

    For validation: its rows come in placements (two actuations each in the shipped data),
    and each placement's scene parts cost the same again for every row. Inference and
    export stay on the plain path (a prediction is one scene; ``TubeNet.cache``).
    """
    return _set(_SHARED)


def encoder_bf16(enabled: bool = True):
    """
    Within it (if ``enabled``), :class:`SceneEncoder` runs its convolutions in bfloat16.

    For training steps (``TrainConfig.encoder_bf16``): the convolutions are nearly all of a
    reader step's time, and take about 0.6 as long in bfloat16 on a CPU with AVX-512 BF16.
    What they feed (the code's MLP, the keypoint heads, the renderer) stays float32, as do
    validation, inference and export, outside the context.
    """
    return _set(_BF16, bool(enabled))


def scene_nets_bf16(enabled: bool = True):
    """
    Within it (if ``enabled``), :class:`ObjectNet` and :class:`BackgroundNet` run in bfloat16.

    For the full loss's training steps (``TrainConfig.scene_nets_bf16``): their convolutions
    were a fifth of a step's time. Their heads, the layers that draw the occupancy, depth
    and fill, stay float32, as does everything outside the context (docs/model.md, "The
    scene nets in bfloat16").
    """
    return _set(_BF16_NETS, bool(enabled))


def compiled_renderer(enabled: bool = True):
    """
    Within it (if ``enabled``), steps with gradients draw the tube with a compiled renderer.

    For the full loss's training steps (``TrainConfig.compile_renderer``): the renderer's
    per-pixel field is some thirty elementwise passes over B x V x S x S tensors, twice a
    step (the prediction and the teacher), each through memory; ``torch.compile`` fuses
    them. The same formula, float rounding aside. Validation, inference and export stay on
    the plain path (docs/model.md, "A compiled renderer").
    """
    return _set(_COMPILED, bool(enabled))


@functools.cache
def _compiled_field():
    return torch.compile(tube_field)


def draw_field(keypoints: torch.Tensor, size: int) -> TubeField:
    """Return :func:`~softshape_ros.model.tube_render.tube_field`, compiled where asked."""
    if _COMPILED.get() and torch.is_grad_enabled() and not torch.compiler.is_compiling():
        return _compiled_field()(keypoints, size)
    return tube_field(keypoints, size)


@functools.cache
def check_renderer_compiles() -> None:
    """
    Compile a small renderer and run it forward and backward; raise RuntimeError if it fails.

    ``torch.compile`` builds C++ kernels: on a machine without a working compiler the
    first training step would fail, after whatever came before it. Checked up front
    instead, once per process, in a frame of its own (so its shapes do not make the
    training's compile a dynamic one).
    """
    kp = torch.tensor([[[[4.0, 2.0, 1.5, 0.0], [4.0, 6.0, 1.0, 1.0]]]], requires_grad=True)
    try:
        torch.compile(lambda k: tube_field(k, 8).sd.sum())(kp).backward()
    except Exception as e:      # the backends raise many kinds; each means the same here
        cause = (str(e).strip().splitlines() or [''])[0][:300]
        raise RuntimeError(f'torch.compile could not build the renderer here ({type(e).__name__}'
                           f': {cause}); it needs a working C++ compiler') from e


def cpu_bf16_native(cpuinfo: str | Path = '/proc/cpuinfo') -> bool:
    """
    Whether this CPU has bfloat16 instructions (x86 AVX-512 BF16 or AMX, Arm BF16).

    Where it has not, :func:`encoder_bf16` may cost time instead of saving it (oneDNN
    emulates them). ``torch.ops.mkldnn._is_mkldnn_bf16_supported`` is no answer: it is
    true on any AVX-512 CPU. Without ``cpuinfo`` (not Linux): that answer.
    """
    try:
        flags = set(Path(cpuinfo).read_text().split())
    except OSError:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return bool(flags & {'avx512_bf16', 'amx_bf16', 'bf16'})


def per_scene(fn, image: torch.Tensor) -> tuple:
    """
    Return ``fn(image)`` (a tuple of B x ... tensors), run once per distinct rest image.

    Rows of one placement share their rest images, and what is made of those alone (the
    scene code, the background) is the same for each: a batch of whole placements
    (``TrainConfig.scene_batch``) pays for the placements, not the rows. Without gradients
    only within :func:`scenes_shared` (validation).
    """
    if torch.compiler.is_compiling() or not (torch.is_grad_enabled() or _SHARED.get()):
        return tuple(fn(image))                                    # inference, export
    unique, inverse = torch.unique(image.flatten(1), dim=0, return_inverse=True)
    if len(unique) == len(image):
        return tuple(fn(image))
    return tuple(t[inverse] for t in fn(unique.view(-1, *image.shape[1:])))


class SceneEncoder(nn.Module):
    """
    Rest images -> a scene code (B x code) and what the code says of the object (B x 17).

    Strided convolutions (GroupNorm, ReLU) over the stacked views, less the training set's
    mean rest image and over its per-pixel spread, down to S/16; an MLP (LayerNorm) of the
    flattened map, which keeps where things are, to the code. It never sees
    the pressures: one code per scene (inference caches it). The second output reads the
    object's kind, position and size back out of the code
    (:data:`~softshape_ros.model.data.SCENE_FEATURES`, in units of the training placements'
    spread), so that where the placement is known (the simulator; a session YAML) training
    can tell the encoder what to see. Why the mean image and the norms: rest images differ
    only where the object is; on the raw images every scene gave the same features and
    the convolutions' ReLUs died within 300 steps (99 % zeros), the code constant.
    """

    def __init__(self, channels: int, size: int, widths=(32, 64, 96, 128), code: int = 64,
                 hidden: int = 512):
        super().__init__()
        layers, cin = [], channels
        for w in widths:
            layers += [down_conv(cin, w), nn.GroupNorm(8, w), nn.ReLU(),
                       nn.Conv2d(in_channels=w, out_channels=w, kernel_size=3, padding=1),
                       nn.GroupNorm(8, w), nn.ReLU()]
            cin = w
        self.convs = nn.Sequential(*layers)
        feat = widths[-1] * (size // 2 ** len(widths)) ** 2
        self.code = nn.Sequential(nn.Linear(feat, hidden), nn.LayerNorm(hidden), nn.ReLU(),
                                  nn.Linear(hidden, code))
        self.describe = nn.Linear(code, len(SCENE_FEATURES))
        self.register_buffer('mean_image', torch.zeros(channels, size, size))
        self.register_buffer('std_image', torch.ones(channels, size, size))
        self.register_buffer('mean', torch.zeros(len(SCENE_FEATURES)))
        self.register_buffer('spread', torch.ones(len(SCENE_FEATURES)))

    def set_stats(self, images: torch.Tensor, targets: torch.Tensor | None = None) -> None:
        """Take the mean of N x VC x S x S training rest images, and of N x 17 targets."""
        self.mean_image.copy_(images.mean(0))
        if len(images) > 1:
            self.std_image.copy_(images.std(0).clamp_min(0.02))
        if targets is not None and len(targets) > 1:
            self.mean.copy_(targets.mean(0))
            self.spread.copy_(targets.std(0).clamp_min(1.0))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = (image - self.mean_image) / self.std_image               # B x VC x S x S
        with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=_BF16.get()):
            f = self.convs(x)                                        # B x 128 x S/16 x S/16
        z = self.code(f.to(x.dtype).flatten(1))                      # B x code
        return z, self.mean + self.spread * self.describe(z)         # B x 17


class KeypointNet(nn.Module):
    """
    Pressures and a scene code -> B x V x K x 4 keypoints: the free shape + the object's push.

    The free shape is an MLP of the pressures alone; the correction an MLP of the pressures
    and the :class:`SceneEncoder`'s code. Why this split: given the object's true placement,
    an MLP of it and the pressures predicts the touching robot's tip within 0.8 px on unseen
    placements (docs/model.md); what is hard is seeing the placement, which the encoder
    learns once per scene instead of once per actuation.
    """

    def __init__(self, views: int, channels: int, keypoints: int, size: int,
                 cond: int = 64, hidden: int = 512, code: int = 64):
        super().__init__()
        self.views, self.k = views, keypoints
        out = views * keypoints * 4
        # Until set_template: a straight tube down the middle of the image.
        template = torch.zeros(views, keypoints, 4)
        template[..., X] = 0.5 * size - 0.5
        template[..., Y] = torch.linspace(0.1 * size, 0.9 * size, keypoints)
        template[..., R] = size / 16
        self.register_buffer('template', template)
        self.register_buffer('scale', torch.tensor(KEYPOINT_SCALE))
        self.free = mlp(N_PRESSURES, 128, out)
        # The pressures' embedding, for the visibility network's FiLM.
        self.cond = nn.Sequential(nn.Linear(N_PRESSURES, cond), nn.ReLU(),
                                  nn.Linear(cond, cond), nn.ReLU())
        self.scene = SceneEncoder(views * channels, size, code=code, hidden=hidden)
        self.correct = nn.Sequential(nn.Linear(N_PRESSURES + code, hidden), nn.ReLU(),
                                     mlp(hidden, hidden, out))

    def rest(self) -> torch.Tensor:
        """Return the free shape at zero pressure (V x K x 4): the resting robot."""
        zero = self.scale.new_zeros(1, N_PRESSURES)
        return self.template + self.free(zero).view(self.views, self.k, 4) * self.scale

    def forward(self, code: torch.Tensor, pressure: torch.Tensor):
        """B x code scene codes + B x 6 pressures -> (keypoints, free keypoints, embedding)."""
        shape = (pressure.shape[0], self.views, self.k, 4)
        free = self.template + self.free(pressure).view(shape) * self.scale
        corr = self.correct(torch.cat([pressure, code], 1)).view(shape) * self.scale
        return free + corr, free, self.cond(pressure)


class ObjectNet(nn.Module):
    """
    Rest images + scene code -> per view where the object is and how near its front is.

    Returns B x V x S x S occupancy logits and B x V x S x S depth of the object's front
    surface (px further from the camera than the robot's base: the shape record's depth).
    A U-Net down to S/8 with the scene code added at the bottom and the full-resolution
    features kept to the head, so the silhouette's edge lands on the image's pixels. Why:
    with it the composite hides the robot by a depth test (:meth:`TubeNet.render`). Drawn
    from the true keypoints and the object's true depth, that test took the robot drawn over
    objects from 1.6 % of their pixels (the learned visibility) to 0.1 % (docs/model.md,
    "A depth test"). Its head starts at "no object anywhere": nothing hidden.
    """

    DEPTH_SCALE = 16.0              # px per unit of the depth output

    def __init__(self, views: int, channels: int, code: int = 64, widths=(16, 32, 64)):
        super().__init__()
        self.views = views
        w0, w1, w2 = widths
        self.inp = nn.Sequential(nn.Conv2d(in_channels=views * channels + 2, out_channels=w0,
                                           kernel_size=3, padding=1), nn.GroupNorm(4, w0),
                                 nn.ReLU())
        self.down = nn.ModuleList([nn.Sequential(down_conv(a, b), nn.GroupNorm(8, b), nn.ReLU())
                                   for a, b in ((w0, w1), (w1, w2), (w2, w2))])
        self.code = nn.Linear(code, w2)
        self.up = nn.ModuleList([nn.Sequential(up_conv(a, b), nn.GroupNorm(8, b), nn.ReLU())
                                 for a, b in ((w2, w2), (2 * w2, w1), (2 * w1, w0))])
        self.head = nn.Conv2d(in_channels=2 * w0, out_channels=2 * views, kernel_size=3,
                              padding=1)
        nn.init.zeros_(self.head.weight)
        with torch.no_grad():
            self.head.bias.copy_(torch.tensor([-4.0] * views + [0.0] * views))

    def forward(self, image: torch.Tensor, code: torch.Tensor):
        """B x VC x S x S rest images + B x code -> (occupancy logits, depth px), B x V x S x S."""
        b, _, h, w = image.shape
        with torch.autocast(image.device.type, dtype=torch.bfloat16, enabled=_BF16_NETS.get()):
            x = self.inp(torch.cat([image, coordinate_planes(b, h, w, image)], 1))  # B x w0 x S
            skips = [x]
            for stage in self.down:                                  # S/2, S/4, S/8
                x = stage(x)
                skips.append(x)
            x = x + self.code(code)[:, :, None, None]
            skips.pop()
            for stage in self.up:                                    # S/4, S/2, S
                x = torch.cat([stage(x), skips.pop()], 1)
        occ, depth = self.head(x.to(image.dtype)).split(self.views, 1)
        return occ, depth * self.DEPTH_SCALE


class BackgroundNet(nn.Module):
    """
    The rest image with the resting robot erased: kept outside its tube, filled inside.

    The resting robot's tube (the free shape at zero pressure, widened by ``MARGIN_PX``)
    masks the rest image; a small U-Net over the rest image and that mask fills the
    masked pixels (what the robot hid: background, or the object behind it), as a change
    from the scene's mean shade away from the robot (its head starts at zero): the fill
    starts as the backdrop instead of mid-grey, and a logit near its target keeps the
    sigmoid out of saturation.
    """

    MARGIN_PX = 1.5

    def __init__(self, views: int, channels: int, widths=(16, 32, 32)):
        super().__init__()
        self.views, self.channels = views, channels
        self.down = nn.ModuleList()
        c = views * channels + views + 2
        for w in widths:
            self.down.append(nn.Sequential(down_conv(c, w), nn.ReLU()))
            c = w
        self.up = nn.ModuleList()
        for w in reversed(widths[:-1]):
            self.up.append(nn.Sequential(up_conv(2 * c if self.up else c, w), nn.ReLU()))
            c = w
        self.head = up_conv(2 * c, views * channels)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, image: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
        """B x VC x S x S rest images + V x K x 4 rest keypoints -> the backgrounds."""
        b, _, h, w = image.shape
        v, c = self.views, self.channels
        widened = rest + torch.tensor([0.0, 0.0, self.MARGIN_PX, 0.0], dtype=rest.dtype)
        mask = coverage(tube_field(widened[None], h).sd).view(1, v, h, w).expand(b, v, h, w)
        x = torch.cat([image, mask, coordinate_planes(b, h, w, image)], 1)
        skips = []
        with torch.autocast(image.device.type, dtype=torch.bfloat16, enabled=_BF16_NETS.get()):
            for stage in self.down:                                  # S/2, S/4, S/8
                x = stage(x)
                skips.append(x)
            skips.pop()
            for stage in self.up:                                    # S/4, S/2
                x = torch.cat([stage(x), skips.pop()], 1)
        x = x.to(image.dtype)
        m = mask[:, :, None]                                         # B x V x 1 x S x S
        img = image.view(b, v, c, h, w)
        level = (img * (1 - m)).sum((3, 4)) / (1 - m).sum((3, 4)).clamp_min(1.0)  # B x V x C
        prior = torch.logit(level.clamp(0.02, 0.98))[..., None, None]
        fill = torch.sigmoid(self.head(x).view(b, v, c, h, w) + prior)  # B x V x C x S x S
        return (m * fill + (1 - m) * img).view(b, v * c, h, w)


class VisibilityNet(nn.Module):
    """
    Per pixel: is the robot in front (1) or hidden by the object (0)? Logits at S x S.

    A FiLM CNN at half resolution (the inputs averaged 2x2, the logits upsampled
    bilinearly). ``code`` > 0 (``TubeNet(scene_visibility=True)``, what training builds):
    the FiLM also reads the scene code, and a full-resolution 3x3 head sharpens the
    upsampled logits along the object's edge. Why: which of robot and object is nearer
    the camera depends on where the object stands in 3-D, which no local filter over
    stacked, unaligned views can see; the code knows the placement. Measured with the true
    keypoints drawn (docs/model.md), the pressure-only net let the side view draw the
    robot through a cylinder in front of it: 3.3 % of the object's pixels.
    """

    def __init__(self, views: int, channels: int, cond: int, width: int = 16, code: int = 0):
        super().__init__()
        cin = views * channels + 2 * views + 2
        self.inp = nn.Sequential(nn.Conv2d(in_channels=cin, out_channels=width, kernel_size=3,
                                           padding=1), nn.ReLU())
        self.down = Stage(down_conv(width, 2 * width), 2 * width)
        self.mid = Stage(nn.Conv2d(in_channels=2 * width, out_channels=2 * width, kernel_size=3,
                                   padding=2, dilation=2), 2 * width)
        self.up = up_conv(2 * width, width)
        self.head = nn.Conv2d(in_channels=2 * width, out_channels=views, kernel_size=3,
                              padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.constant_(self.head.bias, 4.0)          # visible everywhere at the start
        self.split = [4 * width, 4 * width]
        self.code = int(code)
        self.film = nn.Linear(cond + self.code, sum(self.split))
        nn.init.zeros_(self.film.weight)
        nn.init.zeros_(self.film.bias)
        self.fine = None
        if self.code:
            self.fine = nn.Sequential(
                nn.Conv2d(in_channels=cin + views, out_channels=width, kernel_size=3, padding=1),
                nn.ReLU(),
                nn.Conv2d(in_channels=width, out_channels=views, kernel_size=3, padding=1))
            nn.init.zeros_(self.fine[-1].weight)
            nn.init.zeros_(self.fine[-1].bias)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """B x cin x S x S inputs + B x (cond + code) conditioning -> B x V x S x S logits."""
        s = x.shape[-1]
        f1, f2 = self.film(cond)[:, :, None, None].split(self.split, 1)
        x0 = self.inp(F.avg_pool2d(x, 2))                            # B x w x S/2 x S/2
        h = self.mid(self.down(x0, *f1.chunk(2, 1)), *f2.chunk(2, 1))  # B x 2w x S/4
        logit = self.head(torch.cat([torch.relu(self.up(h)), x0], 1))  # B x V x S/2
        logit = F.interpolate(logit, size=(s, s), mode='bilinear', align_corners=False)
        if self.fine is not None:                                    # B x V x S x S
            logit = logit + self.fine(torch.cat([x, logit], 1))
        return logit


def rest_template(initial, silhouette, views: int, keypoints: int) -> torch.Tensor:
    """
    Return V x K x 4 keypoints of the resting robot read off rest images (no shape record).

    Per view the robot's pixels of the typical rest image (the silhouette's threshold): a
    straight tube from the top of its outline to the bottom, through the middle of each
    row, as wide as its median row; depth 0.
    """
    import numpy as np
    img = np.asarray(initial)
    n, vc, s, _ = img.shape
    mask = silhouette.mask(img.reshape(n, views, vc // views, s, s)).mean(0) > 0.5
    out = np.zeros((views, keypoints, 4), np.float32)
    for v in range(views):
        rows = np.nonzero(mask[v].any(1))[0]
        if len(rows) < 2:               # no robot seen: a vertical tube down the middle
            rows = np.array([0, s - 1])
        widths = mask[v][rows].sum(1)
        r = max(1.0, 0.5 * float(np.median(widths)))
        top, bottom = rows[0] - 0.5 + r, rows[-1] + 0.5 - r
        ys = np.linspace(top, max(top, bottom), keypoints)
        cols = np.arange(s)
        centre = [(mask[v][y] * cols).sum() / max(mask[v][y].sum(), 1) if mask[v][y].any()
                  else s / 2 - 0.5 for y in np.clip(np.rint(ys).astype(int), 0, s - 1)]
        out[v, :, 0], out[v, :, 1], out[v, :, 2] = centre, ys, r
    return torch.from_numpy(out)


class TubeNet(nn.Module):
    """The structured forward model (see the module notes); ``forward`` returns the image."""

    def __init__(self, views: int, channels: int, keypoints: int = KEYPOINTS, size: int = 64,
                 cond: int = 64, scene_visibility: bool = False, outline: bool = False,
                 depth_test: bool = False, members: int = 1):
        super().__init__()
        self.views, self.channels, self.size = int(views), int(channels), int(size)
        self.keypoints = KeypointNet(views, channels, keypoints, size, cond=cond)
        if int(members) < 1:
            raise ValueError(f'members {members}: an ensemble has at least one')
        # An ensemble's other keypoint networks (see the module notes); none by default, so
        # checkpoints of one training hold the same tensors as before.
        self.members = nn.ModuleList(KeypointNet(views, channels, keypoints, size, cond=cond)
                                     for _ in range(int(members) - 1))
        self.background = BackgroundNet(views, channels)
        code = self.keypoints.scene.describe.in_features
        # True (``softshape train --depth-test``): the robot is hidden where ObjectNet puts
        # the object nearer than the tube's surface; False (checkpoints that record no
        # ``depth_test``): the learned VisibilityNet decides. docs/model.md, "A depth test".
        self.depth_test = bool(depth_test)
        # False: the visibility of checkpoints made before it saw the scene code (they
        # record no ``scene_visibility``); training builds True (train._network).
        self.scene_visibility = bool(scene_visibility)
        if self.depth_test:
            self.objects, self.visibility = ObjectNet(views, channels, code=code), None
        else:
            self.objects = None
            self.visibility = VisibilityNet(views, channels, cond,
                                            code=code if scene_visibility else 0)
        # True: the shader learns how far out the drawn outline lies (``softshape train
        # --outline``); False (the shipped recipe, and checkpoints that record no
        # ``outline``): the edge at the keypoints' radius. docs/model.md, "The outline".
        self.outline = bool(outline)
        self.shader = TubeShader(views, channels, outline=self.outline)
        self.cache = False              # inference: keep the last scene's SceneParts
        self._cached = None

    def set_template(self, keypoints: torch.Tensor) -> None:
        """Set the keypoint template (V x K x 4, px): the shape the heads start from."""
        self.keypoints.template.copy_(keypoints)

    def scene_parts(self, image: torch.Tensor) -> SceneParts:
        """Return what depends on the rest images alone: once per scene while ``cache`` is on."""
        if not self.cache or torch.is_grad_enabled():
            return self._scene_parts(image)
        c = self._cached
        if c is None or c[0].shape != image.shape or not torch.equal(c[0], image):
            b = image.shape[0]
            if b > 1 and torch.equal(image[1:], image[:1].expand(b - 1, *image.shape[1:])):
                # One scene, many actuations (a planner's candidates): its parts once.
                one = self._scene_parts(image[:1])
                parts = SceneParts(*(t.expand(b, *t.shape[1:]) for t in one))
            else:
                parts = self._scene_parts(image)
            c = self._cached = (image.clone(), parts)
        return c[1]

    def _scene_parts(self, image: torch.Tensor) -> SceneParts:
        return SceneParts(*per_scene(self._one_scene_parts, image))

    def _one_scene_parts(self, image: torch.Tensor) -> tuple:
        code, described = self.keypoints.scene(image)
        # Without the depth test, B x 0 (a slice: keeps the batch size symbolic for export).
        objects = (torch.cat(self.objects(image, code), 1) if self.depth_test
                   else image.flatten(1)[:, :0])
        return (code, described, self.background(image, self.keypoints.rest()), objects,
                self._member_codes(image))

    def _member_codes(self, image: torch.Tensor) -> torch.Tensor:
        """B x VC x S x S rest images -> B x (M - 1) code: the other members' scene codes."""
        if not len(self.members):
            return image.flatten(1)[:, :0]
        return torch.cat([m.scene(image)[0] for m in self.members], 1)

    def _mean_keypoints(self, kp, free, member_codes, pressure):
        """Return the members' mean keypoints and free keypoints (B x V x K x 4 each)."""
        if not len(self.members):
            return kp, free
        kps, frees = [kp], [free]
        for m, code in zip(self.members, member_codes.chunk(len(self.members), 1)):
            k, f, _ = m(code, pressure)
            kps.append(k)
            frees.append(f)
        return torch.stack(kps).mean(0), torch.stack(frees).mean(0)

    def render(self, keypoints, image, background, cond, objects):
        """
        Compose the tube over ``background``: (image, alpha, coverage, visibility logits).

        ``objects``: :attr:`SceneParts.objects`. With ``depth_test`` the robot is hidden
        where the object is (its occupancy) and its front is nearer than the tube's surface;
        else the VisibilityNet's logits decide.
        """
        b, v, c, s = image.shape[0], self.views, self.channels, self.size
        field: TubeField = draw_field(keypoints, s)
        cov = self.shader.coverage(field).view(b, v, s, s)
        if self.depth_test:
            occ, obj_depth = objects.reshape(b, 2, v, s * s).unbind(1)       # B x V x P
            hidden = torch.sigmoid(occ) * torch.sigmoid(
                (front_depth(field) - obj_depth) / DEPTH_SOFT_PX)
            visible = (1.0 - hidden).view(b, v, s, s)
            logit = torch.logit(visible.clamp(1e-6, 1.0 - 1e-6))
            alpha = cov * visible                                    # B x V x S x S
        else:
            depth = (field.depth / keypoints[:, :, :1, R].clamp_min(0.5)).view(b, v, s, s)
            logit = self.visibility(torch.cat([image, cov, depth * cov,
                                               coordinate_planes(b, s, s, image)], 1), cond)
            alpha = cov * torch.sigmoid(logit)                       # B x V x S x S
        shade = self.shader(field).view(b, v, c, s, s)
        a = alpha[:, :, None]
        out = a * shade + (1 - a) * background.view(b, v, c, s, s)
        return out.view(b, v * c, s, s), alpha, cov, logit

    def forward(self, image: torch.Tensor, pressure: torch.Tensor,
                truth: torch.Tensor | None = None, parts: bool = False):
        """
        B x VC x S x S images in [0, 1] + B x 6 pressures -> the predicted images.

        ``parts``: return the whole :class:`TubeOutput` instead (``'keypoints'``: only the
        keypoints, the free shape and the scene description, nothing drawn; ``'codes'``: the
        same from ``image`` B x code scene codes, the description None); ``truth`` (B x V x
        K x 4, the shape record) also draws the composite from the true keypoints.
        """
        if parts == 'codes':            # the keypoint heads alone (a frozen encoder's codes)
            if len(self.members):
                raise ValueError('an ensemble\'s members have their own codes: train each '
                                 'member, then average them (softshape ensemble)')
            return (*self.keypoints(image, pressure)[:2], None)
        if parts == 'keypoints':
            code, described = per_scene(self.keypoints.scene, image)
            kp, free, _ = self.keypoints(code, pressure)
            if len(self.members):       # (one training: no second pass over the scenes)
                members = per_scene(lambda i: (self._member_codes(i),), image)[0]
                kp, free = self._mean_keypoints(kp, free, members, pressure)
            return kp, free, described
        scene = self.scene_parts(image)
        kp, free, cond = self.keypoints(scene.code, pressure)
        kp, free = self._mean_keypoints(kp, free, scene.member_codes, pressure)
        if self.scene_visibility:
            cond = torch.cat([cond, scene.code], 1)                  # B x (cond + code)
        # With the shape record the background learns only where the scene is seen without
        # the robot (TubeLoss): through the composites, the robot's rim errors were paid for
        # by a fill turned white (0.998 against a 0.94 backdrop).
        bg = scene.background if truth is None else scene.background.detach()
        out, alpha, _, _ = self.render(kp, image, bg, cond, scene.objects)
        if not parts:
            return out
        teacher, _, cov, vis = (None,) * 4 if truth is None else self.render(
            truth, image, bg, cond, scene.objects)
        occ, obj_depth = (scene.objects.split(self.views, 1) if self.depth_test
                          else (None, None))
        return TubeOutput(out, kp, free, scene.background, alpha, teacher, cov, vis,
                          scene.described, occ, obj_depth)
