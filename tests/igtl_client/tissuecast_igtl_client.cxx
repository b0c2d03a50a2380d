// A small OpenIGTLink client built with the official OpenIGTLink C++ library (Debian
// libopenigtlink-dev), used by tests/serve/test_serve_cpp_client.py to check the tissuecast server
// against software nobody here wrote.
//
// Usage: tissuecast_igtl_client HOST PORT REGISTRATION_NAME M00 .. M33 X0 Y0 Z0 [X1 Y1 Z1 ...]
//   1. sends TRANSFORM REGISTRATION_NAME (the 4x4 matrix, row by row), then POINT "Markers"
//      (the marker positions, mm) and prints the POLYDATA reply, unpacked with the library's
//      CRC check: "POLYDATA <device> <crc ok 0/1> <points> <polygons> <attributes>", then
//      "P x y z" per point, "T i j k" per triangle, "A name components size" per attribute;
//   2. sends malformed messages and prints each reply ("STRING <device> <crc ok> <text>"):
//      a POINT whose body no longer matches its CRC, a POINT with one marker missing, a
//      TRANSFORM for an unknown device;
//   3. sends a header of an unknown version and prints the reply, then "CLOSED" when the
//      server drops the connection.
// Any STATUS message (the out-of-distribution alarm) is printed where it arrives:
// "STATUS <device> <crc ok> <code> <subcode> <error name> <message>".
//
// Usage: tissuecast_igtl_client HOST PORT --latency FRAMES DEVICE PAUSE_MS M00 .. M33 X0 Y0 Z0 [...]
//   timing (benchmarks/igtl_latency.py): per frame TRANSFORM DEVICE (none when DEVICE is "-") and
//   POINT "Markers" (the markers moved a little each frame), then the POLYDATA reply; prints
//   "R <microseconds>" per frame from the first send to the reply unpacked, after 20 warm-up
//   frames; PAUSE_MS milliseconds (decimals allowed, 0 = back to back) pass between a reply and
//   the next frame, as when a tracker streams at a fixed rate. Exit status 3 on a reply that is
//   not the surface.
//
// Usage: tissuecast_igtl_client HOST PORT --instrument DEVICE WAIT_MS M00 .. M33 X0 Y0 Z0 [...]
//   a tracked instrument: POINT "Markers" (no instrument yet), then TRANSFORM DEVICE (the tool's
//   4x4 pose, row by row) and POINT again, then after WAIT_MS milliseconds POINT again; after each
//   POINT it prints the two replies (POLYDATA, then the STATUS saying whether the instrument is
//   tracked), as above.
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <list>
#include <string>
#include <thread>
#include <vector>

#include "igtlClientSocket.h"
#include "igtlMessageHeader.h"
#include "igtlPointMessage.h"
#include "igtlPolyDataMessage.h"
#include "igtlStatusMessage.h"
#include "igtlStringMessage.h"
#include "igtlTransformMessage.h"

static int sendPoints(igtl::ClientSocket::Pointer& socket, const std::vector<float>& xyz, size_t count, bool corrupt)
{
  igtl::PointMessage::Pointer message = igtl::PointMessage::New();
  message->SetDeviceName("Markers");
  for (size_t i = 0; i < count; ++i)
  {
    igtl::PointElement::Pointer point = igtl::PointElement::New();
    char name[32];
    std::snprintf(name, sizeof(name), "M%zu", i);
    point->SetName(name);
    point->SetGroupName("Fiducial");
    point->SetRGBA(255, 0, 0, 255);
    point->SetPosition(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]);
    point->SetRadius(2.0);
    point->SetOwner("");
    message->AddPointElement(point);
  }
  message->Pack();
  if (corrupt)
  {
    // change one coordinate byte after packing: the header's CRC no longer matches the body
    static_cast<unsigned char*>(message->GetPackBodyPointer())[100] ^= 0x5A;
  }
  return socket->Send(message->GetPackPointer(), message->GetPackSize());
}

static int sendTransform(igtl::ClientSocket::Pointer& socket, const char* name, const float m[16])
{
  igtl::TransformMessage::Pointer message = igtl::TransformMessage::New();
  message->SetDeviceName(name);
  igtl::Matrix4x4 matrix;
  for (int r = 0; r < 4; ++r)
    for (int c = 0; c < 4; ++c)
      matrix[r][c] = m[4 * r + c];
  message->SetMatrix(matrix);
  message->Pack();
  return socket->Send(message->GetPackPointer(), message->GetPackSize());
}

// Receives one message and prints it; returns 0 when the server closed the connection.
static int receiveAndPrint(igtl::ClientSocket::Pointer& socket)
{
  igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
  header->InitPack();
  int got = socket->Receive(header->GetPackPointer(), header->GetPackSize());
  if (got == 0)
  {
    std::printf("CLOSED\n");
    return 0;
  }
  if (got != header->GetPackSize())
  {
    std::printf("SHORT_HEADER %d\n", got);
    return 0;
  }
  header->Unpack();
  if (std::strcmp(header->GetDeviceType(), "POLYDATA") == 0)
  {
    igtl::PolyDataMessage::Pointer polydata = igtl::PolyDataMessage::New();
    polydata->SetMessageHeader(header);
    polydata->AllocatePack();
    socket->Receive(polydata->GetPackBodyPointer(), polydata->GetPackBodySize());
    int crcOk = (polydata->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0;
    igtl::PolyDataPointArray::Pointer points = polydata->GetPoints();
    igtl::PolyDataCellArray::Pointer polygons = polydata->GetPolygons();
    int nPoints = points.IsNotNull() ? points->GetNumberOfPoints() : 0;
    int nPolygons = polygons.IsNotNull() ? polygons->GetNumberOfCells() : 0;
    std::printf("POLYDATA %s %d %d %d %d\n", header->GetDeviceName(), crcOk, nPoints, nPolygons,
                polydata->GetNumberOfAttributes());
    for (int i = 0; i < nPoints; ++i)
    {
      igtlFloat32 p[3];
      points->GetPoint(i, p);
      std::printf("P %.9g %.9g %.9g\n", p[0], p[1], p[2]);
    }
    for (int i = 0; i < nPolygons; ++i)
    {
      std::list<igtlUint32> cell;
      polygons->GetCell(i, cell);
      std::printf("T");
      for (std::list<igtlUint32>::iterator it = cell.begin(); it != cell.end(); ++it)
        std::printf(" %u", *it);
      std::printf("\n");
    }
    for (int i = 0; i < polydata->GetNumberOfAttributes(); ++i)
    {
      igtl::PolyDataAttribute* attribute = polydata->GetAttribute(i);
      std::printf("A %s %u %u\n", attribute->GetName(), attribute->GetNumberOfComponents(), attribute->GetSize());
    }
  }
  else if (std::strcmp(header->GetDeviceType(), "STRING") == 0)
  {
    igtl::StringMessage::Pointer text = igtl::StringMessage::New();
    text->SetMessageHeader(header);
    text->AllocatePack();
    socket->Receive(text->GetPackBodyPointer(), text->GetPackBodySize());
    int crcOk = (text->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0;
    std::printf("STRING %s %d %s\n", header->GetDeviceName(), crcOk, text->GetString());
  }
  else if (std::strcmp(header->GetDeviceType(), "STATUS") == 0)
  {
    igtl::StatusMessage::Pointer status = igtl::StatusMessage::New();
    status->SetMessageHeader(header);
    status->AllocatePack();
    socket->Receive(status->GetPackBodyPointer(), status->GetPackBodySize());
    int crcOk = (status->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0;
    std::printf("STATUS %s %d %u %lld %s %s\n", header->GetDeviceName(), crcOk, status->GetCode(),
                static_cast<long long>(status->GetSubCode()), status->GetErrorName(), status->GetStatusString());
  }
  else
  {
    std::printf("OTHER %s %s\n", header->GetDeviceType(), header->GetDeviceName());
    std::vector<char> body(header->GetBodySizeToRead());
    if (!body.empty())
      socket->Receive(&body[0], static_cast<int>(body.size()));
  }
  std::fflush(stdout);
  return 1;
}

// Reads the 4x4 matrix (16 numbers, row by row) at argv[first] and the marker coordinates after
// it; returns false (printing the usage) unless at least one whole marker follows.
static bool readMatrixAndPoints(int argc, char* argv[], int first, const char* usage, float matrix[16],
                                std::vector<float>& xyz)
{
  if (argc < first + 16 + 3 || (argc - first - 16) % 3 != 0)
  {
    std::fprintf(stderr, "usage: %s %s\n", argv[0], usage);
    return false;
  }
  for (int i = 0; i < 16; ++i)
    matrix[i] = static_cast<float>(std::atof(argv[first + i]));
  for (int i = first + 16; i < argc; ++i)
    xyz.push_back(static_cast<float>(std::atof(argv[i])));
  return true;
}

// Receives messages until a POLYDATA (skipping STATUS and reading any other body); returns 1 when
// the POLYDATA's CRC check passed, 0 otherwise or when the connection closed.
static int receivePolyData(igtl::ClientSocket::Pointer& socket, igtl::MessageHeader::Pointer& header,
                           igtl::PolyDataMessage::Pointer& polydata)
{
  for (;;)
  {
    header->InitPack();
    if (socket->Receive(header->GetPackPointer(), header->GetPackSize()) != header->GetPackSize())
      return 0;
    header->Unpack();
    if (std::strcmp(header->GetDeviceType(), "POLYDATA") == 0)
    {
      polydata->SetMessageHeader(header);
      polydata->AllocatePack();
      socket->Receive(polydata->GetPackBodyPointer(), polydata->GetPackBodySize());
      return (polydata->Unpack(1) & igtl::MessageHeader::UNPACK_BODY) ? 1 : 0;
    }
    std::vector<char> body(header->GetBodySizeToRead());
    if (!body.empty())
      socket->Receive(&body[0], static_cast<int>(body.size()));
    if (std::strcmp(header->GetDeviceType(), "STATUS") != 0)
      return 0;
  }
}

static int runLatency(igtl::ClientSocket::Pointer& socket, int argc, char* argv[])
{
  float pose[16];
  std::vector<float> xyz;
  const char* usage = "HOST PORT --latency FRAMES DEVICE PAUSE_MS M00..M33 X0 Y0 Z0 [...]";
  if (!readMatrixAndPoints(argc, argv, 7, usage, pose, xyz))
    return 2;
  if (std::atoi(argv[4]) < 1 || std::atof(argv[6]) < 0.0)
  {
    std::fprintf(stderr, "usage: %s %s (FRAMES at least 1, PAUSE_MS at least 0)\n", argv[0], usage);
    return 2;
  }
  int frames = std::atoi(argv[4]);
  std::chrono::microseconds pause(static_cast<long long>(std::atof(argv[6]) * 1000.0));
  bool tool = std::strcmp(argv[5], "-") != 0;
  size_t count = xyz.size() / 3;
  std::vector<float> moved(xyz.size());
  igtl::MessageHeader::Pointer header = igtl::MessageHeader::New();
  igtl::PolyDataMessage::Pointer polydata = igtl::PolyDataMessage::New();
  const int warmup = 20;
  for (int frame = 0; frame < warmup + frames; ++frame)
  {
    if (frame > 0 && pause.count() > 0)
      std::this_thread::sleep_for(pause);
    for (size_t i = 0; i < xyz.size(); ++i)
      moved[i] = xyz[i] + 0.5f * static_cast<float>(std::sin(0.7 * frame + 1.3 * i));
    std::chrono::steady_clock::time_point start = std::chrono::steady_clock::now();
    if ((tool && !sendTransform(socket, argv[5], pose)) || !sendPoints(socket, moved, count, false))
    {
      std::fprintf(stderr, "frame %d: sending failed (the server closed the connection?)\n", frame);
      return 3;
    }
    if (!receivePolyData(socket, header, polydata))
    {
      std::fprintf(stderr, "frame %d: no POLYDATA reply with a valid CRC\n", frame);
      return 3;
    }
    std::chrono::steady_clock::time_point end = std::chrono::steady_clock::now();
    if (frame >= warmup)
      std::printf("R %lld\n", static_cast<long long>(
                                  std::chrono::duration_cast<std::chrono::microseconds>(end - start).count()));
  }
  std::fflush(stdout);
  socket->CloseSocket();
  return 0;
}

static int runInstrument(igtl::ClientSocket::Pointer& socket, int argc, char* argv[])
{
  float pose[16];
  std::vector<float> xyz;
  if (!readMatrixAndPoints(argc, argv, 6, "HOST PORT --instrument DEVICE WAIT_MS M00..M33 X0 Y0 Z0 [...]", pose, xyz))
    return 2;
  size_t count = xyz.size() / 3;

  sendPoints(socket, xyz, count, false);  // no instrument yet: markers only
  receiveAndPrint(socket);
  receiveAndPrint(socket);
  sendTransform(socket, argv[4], pose);  // the instrument's pose: no reply
  sendPoints(socket, xyz, count, false);
  receiveAndPrint(socket);
  receiveAndPrint(socket);
  std::this_thread::sleep_for(std::chrono::milliseconds(std::atoi(argv[5])));  // its messages stop
  sendPoints(socket, xyz, count, false);
  receiveAndPrint(socket);
  receiveAndPrint(socket);
  socket->CloseSocket();
  return 0;
}

// Connects to argv[1]:argv[2] with a 10 s receive timeout; a null pointer (reason printed) on failure.
static igtl::ClientSocket::Pointer connectTo(char* argv[])
{
  igtl::ClientSocket::Pointer socket = igtl::ClientSocket::New();
  if (socket->ConnectToServer(argv[1], std::atoi(argv[2])) != 0)
  {
    std::fprintf(stderr, "cannot connect to %s:%s\n", argv[1], argv[2]);
    return igtl::ClientSocket::Pointer();
  }
  socket->SetReceiveTimeout(10000);
  return socket;
}

int main(int argc, char* argv[])
{
  bool latency = argc > 3 && std::strcmp(argv[3], "--latency") == 0;
  if (latency || (argc > 3 && std::strcmp(argv[3], "--instrument") == 0))
  {
    igtl::ClientSocket::Pointer socket = connectTo(argv);
    if (socket.IsNull())
      return 1;
    return latency ? runLatency(socket, argc, argv) : runInstrument(socket, argc, argv);
  }
  float matrix[16];
  std::vector<float> xyz;
  if (!readMatrixAndPoints(argc, argv, 4, "HOST PORT REGISTRATION_NAME M00..M33 X0 Y0 Z0 [...]", matrix, xyz))
    return 2;
  igtl::ClientSocket::Pointer socket = connectTo(argv);
  if (socket.IsNull())
    return 1;
  size_t count = xyz.size() / 3;

  sendTransform(socket, argv[3], matrix);  // the registration: no reply
  sendPoints(socket, xyz, count, false);
  receiveAndPrint(socket);  // POLYDATA TissueSurface

  sendPoints(socket, xyz, count, true);  // CRC mismatch
  receiveAndPrint(socket);
  sendPoints(socket, xyz, count - 1, false);  // one marker short
  receiveAndPrint(socket);
  float identity[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  sendTransform(socket, "Needle", identity);  // neither a marker nor a registration
  receiveAndPrint(socket);

  unsigned char garbage[58];
  std::memset(garbage, 0, sizeof(garbage));
  garbage[0] = 0x00;
  garbage[1] = 0x63;  // header version 99
  std::memcpy(garbage + 2, "POINT", 5);
  socket->Send(garbage, sizeof(garbage));
  if (receiveAndPrint(socket))
    receiveAndPrint(socket);  // the server closes a stream it can no longer trust
  socket->CloseSocket();
  return 0;
}
