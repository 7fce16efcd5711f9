"""Procedural and image-textured Principled materials (deterministic, no external downloads)."""

from __future__ import annotations

import bpy
from common import skimage_data_dir


def _principled(name: str):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    if bsdf is None:
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return mat, nt, bsdf


def plain(name, color, roughness=0.5, metallic=0.0, coat=0.0):
    mat, _, bsdf = _principled(name)
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Coat Weight"].default_value = coat
    return mat


def image(name, filename, roughness=0.5, metallic=0.0, coat=0.0, scale=(1.0, 1.0), coord="UV", bump=0.0, tint=None):
    """Image texture from scikit-image's bundled data (CC0 / public domain images)."""
    mat, nt, bsdf = _principled(name)
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.load(str(skimage_data_dir() / filename), check_existing=True)
    tex.interpolation = "Linear"
    tc = nt.nodes.new("ShaderNodeTexCoord")
    mp = nt.nodes.new("ShaderNodeMapping")
    mp.inputs["Scale"].default_value = (scale[0], scale[1], 1.0)
    if coord == "BOX":
        tex.projection = "BOX"
        tex.projection_blend = 0.2
        nt.links.new(tc.outputs["Object"], mp.inputs["Vector"])
    else:
        nt.links.new(tc.outputs[coord], mp.inputs["Vector"])
    nt.links.new(mp.outputs["Vector"], tex.inputs["Vector"])
    color = tex.outputs["Color"]
    if tint is not None:  # multiply a (grey-scale) photo by a colour
        mix = nt.nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.blend_type = "MULTIPLY"
        mix.inputs["Factor"].default_value = 1.0
        nt.links.new(color, mix.inputs["A"])
        mix.inputs["B"].default_value = (*tint, 1.0)
        color = mix.outputs["Result"]
    nt.links.new(color, bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Coat Weight"].default_value = coat
    if bump > 0:
        b = nt.nodes.new("ShaderNodeBump")
        b.inputs["Strength"].default_value = bump
        nt.links.new(tex.outputs["Color"], b.inputs["Height"])
        nt.links.new(b.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def _ramp(nt, fac_socket, c0, c1):
    ramp = nt.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (*c0, 1.0)
    ramp.color_ramp.elements[1].color = (*c1, 1.0)
    nt.links.new(fac_socket, ramp.inputs["Fac"])
    return ramp.outputs["Color"]


def checker(name, c0, c1, scale=12.0, roughness=0.4, metallic=0.0, coord="UV"):
    mat, nt, bsdf = _principled(name)
    tc = nt.nodes.new("ShaderNodeTexCoord")
    ch = nt.nodes.new("ShaderNodeTexChecker")
    ch.inputs["Scale"].default_value = scale
    ch.inputs["Color1"].default_value = (*c0, 1.0)
    ch.inputs["Color2"].default_value = (*c1, 1.0)
    nt.links.new(tc.outputs[coord], ch.inputs["Vector"])
    nt.links.new(ch.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    return mat


def noise(name, c0, c1, scale=8.0, detail=6.0, roughness=0.45, metallic=0.0, coord="Object", bump=0.3):
    mat, nt, bsdf = _principled(name)
    tc = nt.nodes.new("ShaderNodeTexCoord")
    nz = nt.nodes.new("ShaderNodeTexNoise")
    nz.inputs["Scale"].default_value = scale
    nz.inputs["Detail"].default_value = detail
    nt.links.new(tc.outputs[coord], nz.inputs["Vector"])
    nt.links.new(_ramp(nt, nz.outputs["Fac"], c0, c1), bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    if bump > 0:
        b = nt.nodes.new("ShaderNodeBump")
        b.inputs["Strength"].default_value = bump
        nt.links.new(nz.outputs["Fac"], b.inputs["Height"])
        nt.links.new(b.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def voronoi(name, c0, c1, scale=10.0, roughness=0.3, metallic=0.0, coord="Object"):
    mat, nt, bsdf = _principled(name)
    tc = nt.nodes.new("ShaderNodeTexCoord")
    vo = nt.nodes.new("ShaderNodeTexVoronoi")
    vo.inputs["Scale"].default_value = scale
    nt.links.new(tc.outputs[coord], vo.inputs["Vector"])
    nt.links.new(_ramp(nt, vo.outputs["Distance"], c0, c1), bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    return mat


def stripes(name, c0, c1, scale=6.0, roughness=0.35, metallic=0.0, coord="Object"):
    """Wave-texture bands (high-frequency stripes)."""
    mat, nt, bsdf = _principled(name)
    tc = nt.nodes.new("ShaderNodeTexCoord")
    wv = nt.nodes.new("ShaderNodeTexWave")
    wv.inputs["Scale"].default_value = scale
    wv.inputs["Distortion"].default_value = 2.0
    nt.links.new(tc.outputs[coord], wv.inputs["Vector"])
    nt.links.new(_ramp(nt, wv.outputs["Fac"], c0, c1), bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    return mat


def assign(obj, mat):
    obj.data.materials.clear()
    obj.data.materials.append(mat)
    return obj
