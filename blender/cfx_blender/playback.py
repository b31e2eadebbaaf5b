"""Playing a simulation back on the original objects: a MeshSequenceCache modifier per simulated
object that reads its points (stored in the object's local space) from the add-on's USD cache.

The objects keep their materials, parenting and other data; the modifier only replaces vertex
positions (read_data = VERT), which works for meshes and, since Blender 4.x, for Curves objects.
"""

import os
from contextlib import contextmanager

import bpy

MODIFIER_NAME = "CFX Cache"
CACHE_ROOT = "/World"  # where io_usd.cache.CacheWriter puts its prims


def prim_names(objects):
    """A unique, valid USD prim name for each object, keyed by the object's name."""
    from pxr import Tf

    names, taken = {}, set()
    for obj in objects:
        base = Tf.MakeValidIdentifier(obj.name)
        name, n = base, 1
        while name in taken:
            n += 1
            name = f"{base}_{n}"
        taken.add(name)
        names[obj.name] = name
    return names


def cache_modifiers(obj):
    """The add-on's cache modifiers on `obj` (normally one)."""
    return [mod for mod in obj.modifiers if mod.type == 'MESH_SEQUENCE_CACHE' and mod.name.startswith(MODIFIER_NAME)]


@contextmanager
def cache_modifiers_disabled(objects):
    """Switch the add-on's cache modifiers off in viewport and render while the block runs, so that
    the objects' own (unsimulated) geometry is what gets read or exported."""
    saved = []
    for obj in objects:
        for mod in cache_modifiers(obj):
            saved.append((mod, mod.show_viewport, mod.show_render))
            mod.show_viewport = mod.show_render = False
    try:
        yield
    finally:
        for mod, viewport, render in saved:
            mod.show_viewport, mod.show_render = viewport, render


def cache_file_for(path):
    """The CacheFile datablock reading `path`, reloaded if it exists (the file was just rewritten),
    opened otherwise."""
    wanted = os.path.normpath(bpy.path.abspath(path))
    for cache_file in bpy.data.cache_files:
        if os.path.normpath(bpy.path.abspath(cache_file.filepath)) == wanted:
            cache_file.filepath = cache_file.filepath  # assigning the path makes Blender re-read the file
            return cache_file
    before = set(bpy.data.cache_files)
    # there is no bpy.data.cache_files.new(): the open operator creates the datablock
    bpy.ops.cachefile.open(filepath=path)
    created = [cache_file for cache_file in bpy.data.cache_files if cache_file not in before]
    if not created:
        raise RuntimeError(f"{path}: Blender could not open the cache")
    return created[0]


def attach_cache(obj, cache_file, prim_name):
    """Add (or repoint) the add-on's cache modifier on `obj`, last in the stack so it plays back on
    top of whatever the simulation read."""
    modifiers = cache_modifiers(obj)
    mod = modifiers[0] if modifiers else obj.modifiers.new(MODIFIER_NAME, 'MESH_SEQUENCE_CACHE')
    for extra in modifiers[1:]:
        obj.modifiers.remove(extra)
    mod.cache_file = cache_file
    mod.object_path = f"{CACHE_ROOT}/{prim_name}"
    mod.read_data = {'VERT'}
    mod.show_viewport = mod.show_render = True
    return mod


def simulated_objects(scene):
    """(object, modifier) for each object of `scene` that plays back an add-on cache."""
    out = []
    for obj in scene.objects:
        for mod in cache_modifiers(obj):
            if mod.cache_file is not None and mod.object_path:
                out.append((obj, mod))
                break
    return out
