"""DetNet's losses (paper Sec. 3.1 plus ours): heatmap 100 (per-cell MSE, sigma = 1 cell
Gaussians), location 10, delta 1 (squared error weighted by H_gt + 0.1, normalised by the
weight sum, so every joint's map also learns its value away from the peak), a soft-argmax
coordinate loss, presence and handedness BCE 1 (LOSS_WEIGHTS). AdamW's weight decay is L_reg.
"""
# ------------------------------------------------------------------ losses
def gaussian_heatmaps(uv, grid, stride, sigma=1.0):
    """(B,21,2) crop px -> (B,21,G,G) Gaussians of `sigma` cells, peak 1."""
    import torch
    from handmocap.training.detnet import uv_to_cell
    cell = uv_to_cell(uv, stride)
    g = torch.arange(grid, dtype=uv.dtype, device=uv.device)
    dx2 = (g.view(1, 1, 1, grid) - cell[..., 0, None, None]) ** 2
    dy2 = (g.view(1, 1, grid, 1) - cell[..., 1, None, None]) ** 2
    return torch.exp(-0.5 * (dx2 + dy2) / sigma ** 2)


def detnet_losses(out, b, stride):
    """dict of scalar losses (unweighted) for a batch from to_torch."""
    import torch
    import torch.nn.functional as F

    from handmocap.training.detnet import bone_vectors
    heat = out["heatmap"]
    grid = heat.shape[-1]
    h_gt = gaussian_heatmaps(b["uv"], grid, stride)
    w2d = b["w2d"]
    l_heat = ((heat - h_gt) ** 2).mean((1, 2, 3))
    l_heat = (l_heat * w2d).sum() / w2d.sum().clamp_min(1e-6)
    w3d = b["w3d"]
    weight = (h_gt + 0.1).unsqueeze(2)                                      # (B,21,1,G,G)
    weight = weight / weight.sum((3, 4), keepdim=True)

    def map_loss(pred, target):                                             # pred (B,21,3,G,G), target (B,21,3)
        err = (((pred - target[..., None, None]) ** 2) * weight).sum((3, 4)).mean((1, 2))
        return (err * w3d).sum() / w3d.sum().clamp_min(1e-6)
    l_loc = map_loss(out["location"], b["xyz"])
    l_delta = map_loss(out["delta"], bone_vectors(b["xyz"]))
    l_coord = soft_argmax_loss(out["heat_logits"], b["uv"], b["presence"] * w2d, stride)
    fine = {}
    if "fine_logits" in out:        # the same two 2D losses on the fine grid (stride / 2; the same 8 px Gaussians)
        fine_heat = torch.sigmoid(out["fine_logits"])
        l_fine = ((fine_heat - gaussian_heatmaps(b["uv"], 2 * grid, stride / 2, sigma=2.0)) ** 2).mean((1, 2, 3))
        fine = {"fine_heat": (l_fine * w2d).sum() / w2d.sum().clamp_min(1e-6),
                "fine_coord": soft_argmax_loss(out["fine_logits"], b["uv"], b["presence"] * w2d, stride / 2)}
    l_presence = F.binary_cross_entropy_with_logits(out["presence"], b["presence"])
    wh = b["w_hand"]                # balanced between the sides by the batch maker
    l_hand = (F.binary_cross_entropy_with_logits(out["handedness"], b["right"], reduction="none") * wh).sum() \
        / wh.sum().clamp_min(1e-6)
    return {"heat": l_heat, "coord": l_coord, "loc": l_loc, "delta": l_delta, "presence": l_presence,
            "hand": l_hand, **fine}


def soft_argmax_loss(heat_logits, uv, weight, stride):
    """Mean L1 distance in cells between the softmax-expected heatmap position and the label.

    heat_logits (B,21,G,G), uv (B,21,2) crop px, weight (B,) (0 for crops with no hand).
    The per-cell MSE on its own left the heatmaps near zero for the first thousand
    iterations (26 px error at 1,200 on 128 px crops): this term gives every joint a
    gradient towards its label from the first step. Joints outside the crop are skipped.
    """
    from handmocap.training.detnet import soft_argmax, uv_to_cell
    g = heat_logits.shape[-1]
    expected = soft_argmax(heat_logits)[0]                                        # (B,21,2) x, y
    target = uv_to_cell(uv, stride)
    inside = ((target >= -0.5) & (target <= g - 0.5)).all(-1).to(expected.dtype) * weight[:, None]
    err = (expected - target).abs().sum(-1)
    return (err * inside).sum() / inside.sum().clamp_min(1e-6)



LOSS_WEIGHTS = {"heat": 100.0, "coord": 0.5, "loc": 10.0, "delta": 1.0, "presence": 1.0, "hand": 1.0,
                "fine_heat": 100.0, "fine_coord": 0.25}     # fine cells are half as long: the same weight per px
