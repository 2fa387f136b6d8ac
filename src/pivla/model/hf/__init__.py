"""The paper-scale backbone: a local Hugging Face vision-language model fine-tuned with LoRA.

The paper builds CMS on OpenVLA-7B. This backbone reads any Llava-style checkpoint that transformers loads
with ``AutoModelForImageTextToText`` (a vision tower, a projector and a decoder-only language model),
OpenVLA converted by ``pivla convert-openvla`` (plain transformers parts, see ``pivla.model.openvla``), and
OpenVLA's released layout (``model_type`` "openvla": a fused DINOv2 + SigLIP backbone, projector and
Llama-2) through the checkpoint's own code, always from a local directory (nothing is downloaded).

One module per concern, each importable without transformers (it is imported only where a checkpoint is
read or LoRA is applied):

- ``common``: local checkpoint directories;
- ``pixels``: ``PixelSpec``, the checkpoint's pixel preprocessing;
- ``text``: ``HFTextTokenizer``, the checkpoint's tokenizer behind pivla's text interface;
- ``vlm``: loading the model (``load_vlm``, ``resolve_dtype``), uniform access to its parts (``VLMParts``)
  and its vision tower as a target encoder (``VisionPooler``);
- ``lora``: LoRA target layers and activation checkpointing;
- ``backbone``: ``HFBackbone``, the CMS backbone.
"""
