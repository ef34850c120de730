// An Alembic take written by Alembic's own library as a studio's Maya export writes one: a transform
// /take in centimetres (scale 100) over the PolyMesh /take/takeShape, frame 1 at 1/25 s, each frame its
// own topology, UVs an indexed per-corner parameter. Input: the frames as raw arrays (one file each, see
// scripts/abc_from_capture.py). Usage: abc_from_raw OUT.abc FPS FRAME.raw...
#include <Alembic/AbcGeom/All.h>
#include <Alembic/AbcCoreOgawa/All.h>
#include <cstdio>
#include <cstdlib>
#include <vector>

using namespace Alembic::AbcGeom;

template <class T> static std::vector<T> take(FILE *f, size_t n) {
    std::vector<T> v(n);
    if (n && fread(v.data(), sizeof(T), n, f) != n) { fprintf(stderr, "short read\n"); exit(1); }
    return v;
}

int main(int argc, char **argv) {
    double fps = atof(argv[2]);
    OArchive archive = Alembic::Abc::CreateArchiveWithInfo(Alembic::AbcCoreOgawa::WriteArchive(), argv[1],
                                                           "Maya 2024 AbcExport (Alembic 1.8 library)",
                                                           "a volumetric take", MetaData());
    uint32_t tsi = archive.addTimeSampling(TimeSampling(1.0 / fps, 1.0 / fps));
    OXform xf(archive.getTop(), "take", tsi);
    OPolyMesh mesh(xf, "takeShape", tsi);
    XformSample x;
    x.setScale(V3d(100.0, 100.0, 100.0));
    for (int k = 3; k < argc; ++k) {
        FILE *f = fopen(argv[k], "rb");
        int32_t n[3];
        if (!f || fread(n, 4, 3, f) != 3) { fprintf(stderr, "cannot read %s\n", argv[k]); return 1; }
        auto P = take<V3f>(f, n[0]);
        auto idx = take<int32_t>(f, 3 * (size_t)n[1]);
        auto uvs = take<V2f>(f, n[2]);
        auto uvi = take<uint32_t>(f, 3 * (size_t)n[1]);
        fclose(f);
        std::vector<int32_t> counts(n[1], 3);
        xf.getSchema().set(x);
        OV2fGeomParam::Sample uv(V2fArraySample(uvs), UInt32ArraySample(uvi), kFacevaryingScope);
        mesh.getSchema().set(OPolyMeshSchema::Sample(V3fArraySample(P), Int32ArraySample(idx),
                                                     Int32ArraySample(counts), uv));
    }
    return 0;
}
