"""`sine` subcommands of the editing side: features (DINO feature field), masks (semantic
masks), snapshot and target (a view to edit, 2D editing targets), edit (the editing field),
render/export/view/eval
(outputs), demo and batch (built by `sine_cli`)."""

from __future__ import annotations

from edit import (
    batch_cli,
    demo_cli,
    edit_cli,
    eval_cli,
    export_cli,
    features_cli,
    masks_cli,
    render_cli,
    snapshot_cli,
    target_cli,
    view_cli,
)

MODULES = (
    features_cli,
    masks_cli,
    snapshot_cli,
    target_cli,
    edit_cli,
    render_cli,
    export_cli,
    view_cli,
    eval_cli,
    demo_cli,
    batch_cli,
)
