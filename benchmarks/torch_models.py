"""torchvision's classification architectures rebuilt in plain torch.nn, so the benchmarks need torch only.

Each builder follows torchvision's definition (layers, channels, strides, kernel sizes, SE blocks, activations,
residuals, pooling, classifier head and torchvision's own weight initialisation, i.e. `weights=None`); the
parameter counts equal torchvision's (tests/test_real_models.py checks them). `width` scales the channels
the way torchvision's width multipliers do, and `num_classes` the head, for small test models.
Torch is a benchmark-only dependency (the `bench` extra), never imported by nncg itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial

import torch
from torch import nn

Activation = Callable[..., nn.Module] | None


def make_divisible(value: float, divisor: int = 8, min_value: int | None = None) -> int:
    """torchvision's _make_divisible: round to a multiple of `divisor`, never more than 10% below `value`."""
    min_value = min_value or divisor
    new_value = max(min_value, int(value + divisor / 2) // divisor * divisor)
    return new_value + divisor if new_value < 0.9 * value else new_value


def conv_norm_act(
    cin: int, cout: int, kernel: int, stride: int = 1, groups: int = 1, act: Activation = nn.ReLU, eps: float = 1e-5
) -> nn.Sequential:
    """torchvision's Conv2dNormActivation: bias-free conv with "same" padding, BatchNorm, activation."""
    layers: list[nn.Module] = [
        nn.Conv2d(cin, cout, kernel, stride, (kernel - 1) // 2, groups=groups, bias=False),
        nn.BatchNorm2d(cout, eps=eps),
    ]
    if act is not None:
        layers.append(act())
    return nn.Sequential(*layers)


class SqueezeExcitation(nn.Module):
    """torchvision.ops.SqueezeExcitation: global average, 1x1 conv, act, 1x1 conv, gate, scale the input."""

    def __init__(self, channels: int, squeeze: int, act: Callable[..., nn.Module], gate: Callable[..., nn.Module]):
        super().__init__()
        self.avgpool = nn.AdaptiveAvgPool2d(1)
        self.fc1 = nn.Conv2d(channels, squeeze, 1)
        self.fc2 = nn.Conv2d(squeeze, channels, 1)
        self.activation, self.scale_activation = act(), gate()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scale = self.scale_activation(self.fc2(self.activation(self.fc1(self.avgpool(x)))))
        return scale * x


class Residual(nn.Module):
    """x + body(x) when the shapes allow (stride 1, same channels), else body(x): the inverted-residual rule."""

    def __init__(self, body: nn.Module, use_residual: bool):
        super().__init__()
        self.block, self.use_residual = body, use_residual

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.block(x) if self.use_residual else self.block(x)


class Classifier(nn.Module):
    """features, global average pool, flatten, head (torchvision's forward of most of these models)."""

    def __init__(self, features: nn.Module, head: nn.Module):
        super().__init__()
        self.features, self.avgpool, self.classifier = features, nn.AdaptiveAvgPool2d(1), head

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.classifier(torch.flatten(self.avgpool(self.features(x)), 1))


class MeanClassifier(Classifier):
    """As Classifier with `x.mean([2, 3])` for the pool (ShuffleNetV2, MNASNet): exports as ReduceMean."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.classifier(self.features(x).mean([2, 3]))


def init_conv_bn_linear(model: nn.Module, linear: Callable[[nn.Linear], None], conv_nonlinearity="leaky_relu") -> None:
    """The init loop most torchvision models end with: Kaiming-normal (fan_out) convs, identity BatchNorm."""
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity=conv_nonlinearity)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Linear):
            linear(m)


def linear_normal(m: nn.Linear, std: float = 0.01) -> None:
    nn.init.normal_(m.weight, 0, std)
    nn.init.zeros_(m.bias)


# --- MobileNetV2 ------------------------------------------------------------------------------------------


def mobilenet_v2(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    relu6 = partial(nn.ReLU6)
    cin = make_divisible(32 * width)
    last = make_divisible(1280 * max(1.0, width))
    layers: list[nn.Module] = [conv_norm_act(3, cin, 3, 2, act=relu6)]
    # (expansion t, channels c, repeats n, first stride s)
    for t, c, n, s in [(1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 4, 2), (6, 96, 3, 1), (6, 160, 3, 2),
                       (6, 320, 1, 1)]:  # fmt: skip
        cout = make_divisible(c * width)
        for i in range(n):
            stride = s if i == 0 else 1
            hidden = round(cin * t)
            expand = [conv_norm_act(cin, hidden, 1, act=relu6)] if t != 1 else []
            body = nn.Sequential(
                *expand, conv_norm_act(hidden, hidden, 3, stride, groups=hidden, act=relu6),
                conv_norm_act(hidden, cout, 1, act=None),
            )  # fmt: skip
            layers.append(Residual(body, stride == 1 and cin == cout))
            cin = cout
    layers.append(conv_norm_act(cin, last, 1, act=relu6))
    model = Classifier(nn.Sequential(*layers), nn.Sequential(nn.Dropout(0.2), nn.Linear(last, num_classes)))
    init_conv_bn_linear(model, linear_normal)
    return model


# --- MobileNetV3 small --------------------------------------------------------------------------------------


def mobilenet_v3_small(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    bn_eps = 1e-3  # partial(nn.BatchNorm2d, eps=0.001, momentum=0.01) in torchvision
    ch = partial(make_divisible, divisor=8)
    cin = ch(16 * width)
    layers: list[nn.Module] = [conv_norm_act(3, cin, 3, 2, act=nn.Hardswish, eps=bn_eps)]
    # (kernel, expanded, out, SE, activation, stride)
    for k, exp, out, se, hs, s in [
        (3, 16, 16, True, False, 2), (3, 72, 24, False, False, 2), (3, 88, 24, False, False, 1),
        (5, 96, 40, True, True, 2), (5, 240, 40, True, True, 1), (5, 240, 40, True, True, 1),
        (5, 120, 48, True, True, 1), (5, 144, 48, True, True, 1), (5, 288, 96, True, True, 2),
        (5, 576, 96, True, True, 1), (5, 576, 96, True, True, 1),
    ]:  # fmt: skip
        exp, out = ch(exp * width), ch(out * width)
        act = nn.Hardswish if hs else nn.ReLU
        body: list[nn.Module] = [conv_norm_act(cin, exp, 1, act=act, eps=bn_eps)] if exp != cin else []
        body.append(conv_norm_act(exp, exp, k, s, groups=exp, act=act, eps=bn_eps))
        if se:
            body.append(SqueezeExcitation(exp, ch(exp // 4), nn.ReLU, nn.Hardsigmoid))
        body.append(conv_norm_act(exp, out, 1, act=None, eps=bn_eps))
        layers.append(Residual(nn.Sequential(*body), s == 1 and cin == out))
        cin = out
    layers.append(conv_norm_act(cin, 6 * cin, 1, act=nn.Hardswish, eps=bn_eps))
    last = ch(1024 * width)
    head = nn.Sequential(nn.Linear(6 * cin, last), nn.Hardswish(), nn.Dropout(0.2), nn.Linear(last, num_classes))
    model = Classifier(nn.Sequential(*layers), head)
    init_conv_bn_linear(model, linear_normal)
    return model


# --- ResNet-18 ----------------------------------------------------------------------------------------------


class BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU()
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.bn2(self.conv2(self.relu(self.bn1(self.conv1(x)))))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


def resnet18(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    widths = [int(64 * width * 2**i) for i in range(4)]
    layers: list[nn.Module] = [
        nn.Conv2d(3, widths[0], 7, 2, 3, bias=False), nn.BatchNorm2d(widths[0]), nn.ReLU(), nn.MaxPool2d(3, 2, 1),
    ]  # fmt: skip
    cin = widths[0]
    for i, cout in enumerate(widths):
        layers += [BasicBlock(cin, cout, 1 if i == 0 else 2), BasicBlock(cout, cout, 1)]
        cin = cout
    model = Classifier(nn.Sequential(*layers), nn.Linear(cin, num_classes))
    linear_default = lambda m: None  # noqa: E731 - torchvision keeps nn.Linear's own init here
    init_conv_bn_linear(model, linear_default, conv_nonlinearity="relu")
    return model


# --- EfficientNet-B0 ----------------------------------------------------------------------------------------


def efficientnet_b0(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    ch = partial(make_divisible, divisor=8)
    cin = ch(32 * width)
    layers: list[nn.Module] = [conv_norm_act(3, cin, 3, 2, act=nn.SiLU)]
    # MBConv (expansion, kernel, first stride, out channels, repeats); stochastic depth is identity at inference
    for t, k, s, c, n in [(1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3), (6, 5, 1, 112, 3),
                          (6, 5, 2, 192, 4), (6, 3, 1, 320, 1)]:  # fmt: skip
        cout = ch(c * width)
        for i in range(n):
            stride = s if i == 0 else 1
            exp = ch(cin * t)
            body: list[nn.Module] = [conv_norm_act(cin, exp, 1, act=nn.SiLU)] if exp != cin else []
            body += [
                conv_norm_act(exp, exp, k, stride, groups=exp, act=nn.SiLU),
                SqueezeExcitation(exp, max(1, cin // 4), nn.SiLU, nn.Sigmoid),
                conv_norm_act(exp, cout, 1, act=None),
            ]
            layers.append(Residual(nn.Sequential(*body), stride == 1 and cin == cout))
            cin = cout
    layers.append(conv_norm_act(cin, 4 * cin, 1, act=nn.SiLU))
    model = Classifier(nn.Sequential(*layers), nn.Sequential(nn.Dropout(0.2), nn.Linear(4 * cin, num_classes)))

    def linear_uniform(m: nn.Linear) -> None:
        bound = 1.0 / math.sqrt(m.out_features)
        nn.init.uniform_(m.weight, -bound, bound)
        nn.init.zeros_(m.bias)

    init_conv_bn_linear(model, linear_uniform)
    return model


# --- SqueezeNet 1.1 -----------------------------------------------------------------------------------------


class Fire(nn.Module):
    def __init__(self, cin: int, squeeze: int, expand: int):
        super().__init__()
        self.squeeze = nn.Sequential(nn.Conv2d(cin, squeeze, 1), nn.ReLU())
        self.expand1x1 = nn.Sequential(nn.Conv2d(squeeze, expand, 1), nn.ReLU())
        self.expand3x3 = nn.Sequential(nn.Conv2d(squeeze, expand, 3, padding=1), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.squeeze(x)
        return torch.cat([self.expand1x1(x), self.expand3x3(x)], 1)


def squeezenet1_1(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    w = lambda c: max(1, int(c * width))  # noqa: E731
    pool = partial(nn.MaxPool2d, 3, 2, ceil_mode=True)
    features = nn.Sequential(
        nn.Conv2d(3, w(64), 3, 2), nn.ReLU(), pool(),
        Fire(w(64), w(16), w(64)), Fire(w(128), w(16), w(64)), pool(),
        Fire(w(128), w(32), w(128)), Fire(w(256), w(32), w(128)), pool(),
        Fire(w(256), w(48), w(192)), Fire(w(384), w(48), w(192)), Fire(w(384), w(64), w(256)),
        Fire(w(512), w(64), w(256)),
    )  # fmt: skip
    final_conv = nn.Conv2d(w(512), num_classes, 1)
    head = nn.Sequential(nn.Dropout(0.5), final_conv, nn.ReLU(), nn.AdaptiveAvgPool2d(1), nn.Flatten(1))
    model = nn.Sequential(features, head)
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            if m is final_conv:
                nn.init.normal_(m.weight, 0.0, 0.01)
            else:
                nn.init.kaiming_uniform_(m.weight)
            nn.init.zeros_(m.bias)
    return model


# --- ShuffleNetV2 x0.5 --------------------------------------------------------------------------------------


def channel_shuffle(x: torch.Tensor, groups: int) -> torch.Tensor:
    n, c, h, w = x.shape
    return x.view(n, groups, c // groups, h, w).transpose(1, 2).contiguous().view(n, -1, h, w)


class ShuffleBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.stride = stride
        half = cout // 2
        self.branch1 = nn.Sequential()
        if stride > 1:
            self.branch1 = nn.Sequential(
                nn.Conv2d(cin, cin, 3, stride, 1, groups=cin, bias=False), nn.BatchNorm2d(cin),
                nn.Conv2d(cin, half, 1, bias=False), nn.BatchNorm2d(half), nn.ReLU(),
            )  # fmt: skip
        self.branch2 = nn.Sequential(
            nn.Conv2d(cin if stride > 1 else half, half, 1, bias=False), nn.BatchNorm2d(half), nn.ReLU(),
            nn.Conv2d(half, half, 3, stride, 1, groups=half, bias=False), nn.BatchNorm2d(half),
            nn.Conv2d(half, half, 1, bias=False), nn.BatchNorm2d(half), nn.ReLU(),
        )  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.stride == 1:
            x1, x2 = x.chunk(2, dim=1)
            out = torch.cat((x1, self.branch2(x2)), dim=1)
        else:
            out = torch.cat((self.branch1(x), self.branch2(x)), dim=1)
        return channel_shuffle(out, 2)


def shufflenet_v2_x0_5(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    # x0.5's stage channels; `width` scales them further (kept even: the blocks split channels in halves)
    c = [24] + [2 * max(1, int(n * width / 2)) for n in (48, 96, 192)] + [1024]
    layers: list[nn.Module] = [
        nn.Conv2d(3, c[0], 3, 2, 1, bias=False), nn.BatchNorm2d(c[0]), nn.ReLU(), nn.MaxPool2d(3, 2, 1),
    ]  # fmt: skip
    for cin, cout, repeats in zip(c[:3], c[1:4], (4, 8, 4)):
        layers += [ShuffleBlock(cin, cout, 2)] + [ShuffleBlock(cout, cout, 1) for _ in range(repeats - 1)]
    layers += [nn.Conv2d(c[3], c[4], 1, bias=False), nn.BatchNorm2d(c[4]), nn.ReLU()]
    return MeanClassifier(nn.Sequential(*layers), nn.Linear(c[4], num_classes))  # PyTorch's default init


# --- MNASNet 0.5 --------------------------------------------------------------------------------------------


def round_to_multiple_of(value: float, divisor: int, round_up_bias: float = 0.9) -> int:
    """MNASNet's channel rounding: to a multiple of `divisor`, rounding up when it would lose over 10%."""
    new_value = max(divisor, int(value + divisor / 2) // divisor * divisor)
    return new_value if new_value >= round_up_bias * value else new_value + divisor


def mnasnet_block(cin: int, cout: int, kernel: int, stride: int, expansion: int) -> nn.Module:
    mid = cin * expansion
    body = nn.Sequential(
        conv_norm_act(cin, mid, 1), conv_norm_act(mid, mid, kernel, stride, groups=mid),
        conv_norm_act(mid, cout, 1, act=None),
    )  # fmt: skip
    return Residual(body, cin == cout and stride == 1)


def mnasnet0_5(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    d = [round_to_multiple_of(c * 0.5 * width, 8) for c in (32, 16, 24, 40, 80, 96, 192, 320)]
    layers: list[nn.Module] = [
        conv_norm_act(3, d[0], 3, 2), conv_norm_act(d[0], d[0], 3, groups=d[0]), conv_norm_act(d[0], d[1], 1, act=None),
    ]  # fmt: skip
    # stacks of (kernel, first stride, expansion, repeats)
    for cin, cout, (k, s, t, n) in zip(d[1:], d[2:], [(3, 2, 3, 3), (5, 2, 3, 3), (5, 2, 6, 3), (3, 1, 6, 2),
                                                      (5, 2, 6, 4), (3, 1, 6, 1)]):  # fmt: skip
        layers += [mnasnet_block(cin, cout, k, s, t)] + [mnasnet_block(cout, cout, k, 1, t) for _ in range(n - 1)]
    layers.append(conv_norm_act(d[7], 1280, 1))
    model = MeanClassifier(nn.Sequential(*layers), nn.Sequential(nn.Dropout(0.2), nn.Linear(1280, num_classes)))

    def linear_kaiming(m: nn.Linear) -> None:
        nn.init.kaiming_uniform_(m.weight, mode="fan_out", nonlinearity="sigmoid")
        nn.init.zeros_(m.bias)

    init_conv_bn_linear(model, linear_kaiming, conv_nonlinearity="relu")
    return model


# --- RegNetX-400MF ------------------------------------------------------------------------------------------


def regnet_stages(depth: int, w_0: int, w_a: float, w_m: float, group_width: int) -> list[tuple[int, int, int]]:
    """(width, depth, group width) per stage, as torchvision's BlockParams.from_init_params (bottleneck 1)."""
    block_capacity = [round(math.log((i * w_a + w_0) / w_0) / math.log(w_m)) for i in range(depth)]
    widths = [int(round(w_0 * w_m**c / 8) * 8) for c in block_capacity]
    stages: list[list[int]] = []
    for w in widths:
        if stages and stages[-1][0] == w:
            stages[-1][1] += 1
        else:
            stages.append([w, 1])
    result = []
    for w, d in stages:
        g = min(group_width, w)
        result.append((make_divisible(w, g), d, g))
    return result


class RegNetBlock(nn.Module):
    """ResBottleneckBlock (bottleneck multiplier 1, no SE): relu(proj(x) + c(b(a(x))))."""

    def __init__(self, cin: int, cout: int, stride: int, group_width: int):
        super().__init__()
        self.proj = conv_norm_act(cin, cout, 1, stride, act=None) if cin != cout or stride != 1 else None
        self.f = nn.Sequential(
            conv_norm_act(cin, cout, 1), conv_norm_act(cout, cout, 3, stride, groups=cout // group_width),
            conv_norm_act(cout, cout, 1, act=None),
        )  # fmt: skip
        self.activation = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.activation((x if self.proj is None else self.proj(x)) + self.f(x))


def regnet_x_400mf(width: float = 1.0, num_classes: int = 1000) -> nn.Module:
    stem = 32
    layers: list[nn.Module] = [conv_norm_act(3, stem, 3, 2)]
    cin = stem
    for w, depth, g in regnet_stages(22, 24, 24.48, 2.54, 16):
        cout = make_divisible(w * width, g)
        layers += [RegNetBlock(cin if i == 0 else cout, cout, 2 if i == 0 else 1, g) for i in range(depth)]
        cin = cout
    model = Classifier(nn.Sequential(*layers), nn.Linear(cin, num_classes))
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            fan_out = m.kernel_size[0] * m.kernel_size[1] * m.out_channels
            nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / fan_out))
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Linear):
            linear_normal(m)
    return model


ARCHITECTURES: dict[str, Callable[..., nn.Module]] = {
    "mobilenet_v2": mobilenet_v2,
    "mobilenet_v3_small": mobilenet_v3_small,
    "resnet18": resnet18,
    "efficientnet_b0": efficientnet_b0,
    "squeezenet1_1": squeezenet1_1,
    "shufflenet_v2_x0_5": shufflenet_v2_x0_5,
    "mnasnet0_5": mnasnet0_5,
    "regnet_x_400mf": regnet_x_400mf,
}

# torchvision's parameter counts (the weights' meta "num_params"), which pin each architecture down.
TORCHVISION_PARAMS = {
    "mobilenet_v2": 3_504_872,
    "mobilenet_v3_small": 2_542_856,
    "resnet18": 11_689_512,
    "efficientnet_b0": 5_288_548,
    "squeezenet1_1": 1_235_496,
    "shufflenet_v2_x0_5": 1_366_792,
    "mnasnet0_5": 2_218_512,
    "regnet_x_400mf": 5_495_976,
}


def build(name: str, seed: int = 0, **options) -> nn.Module:
    """The architecture in eval mode, its random weights fixed by `seed` (options: width, num_classes)."""
    torch.manual_seed(seed)
    return ARCHITECTURES[name](**options).eval()
